"""report.md and plots (matplotlib, Agg) of a gap diagnosis."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _grid(n):
    cols = min(4, n)
    return (n + cols - 1) // cols, cols


def write_plots(out, diagnosis):
    """Residual vs velocity / acceleration / gravity torque per joint, before/after time series,
    per-joint bars. Returns {name: filename}."""
    plt = _plt()
    out = Path(out)
    d = diagnosis
    check = d.check_designs
    n = check[0].y.shape[1]
    before = np.concatenate(d.check_residual_before)
    after = np.concatenate(d.check_residual_after)
    files = {}
    feats = {"velocity": ("v", "velocity [rad/s]"), "acceleration": ("a", "acceleration [rad/s²]"),
             "gravity": ("g", "gravity torque [N·m]")}
    for key, (f, label) in feats.items():
        x = np.concatenate([c.features[f] for c in check])
        rows, cols = _grid(n)
        fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
        for j in range(rows * cols):
            ax = axes.flat[j]
            if j >= n:
                ax.axis("off")
                continue
            ax.scatter(x[:, j], before[:, j], s=2, c="0.6", label="nominal")
            ax.scatter(x[:, j], after[:, j], s=2, c="tab:blue", label="corrected")
            ax.set_title(f"joint {j + 1}", fontsize=9)
            ax.set_xlabel(label, fontsize=8)
            ax.tick_params(labelsize=7)
            if j % cols == 0:
                ax.set_ylabel("residual [N·m]", fontsize=8)
        axes.flat[0].legend(fontsize=7, markerscale=4)
        fig.suptitle(f"Held-out residual vs {key}", fontsize=10)
        fig.tight_layout()
        name = f"residual_vs_{key}.png"
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        files[key] = name
    # Time series of the first check log.
    c0 = check[0]
    fig, axes = plt.subplots(n, 1, figsize=(9, 1.4 * n + 0.6), sharex=True, squeeze=False)
    for j in range(n):
        ax = axes[j, 0]
        ax.plot(c0.row_time, d.check_residual_before[0][:, j], lw=0.6, c="0.5", label="nominal")
        ax.plot(c0.row_time, d.check_residual_after[0][:, j], lw=0.6, c="tab:blue", label="corrected")
        if c0.row_saturated[:, j].any():
            ax.fill_between(c0.row_time, 0, 1, where=c0.row_saturated[:, j], color="tab:orange", alpha=0.25,
                            transform=ax.get_xaxis_transform(), label="speed-saturated")
        ax.set_ylabel(f"j{j + 1} [N·m]", fontsize=8)
        ax.tick_params(labelsize=7)
    handles = {h.get_label(): h for ax in axes[:, 0] for h in ax.get_legend_handles_labels()[0]}
    axes[0, 0].legend(handles.values(), handles.keys(), fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"Residual before/after, {Path(c0.source).name or 'check log 1'}", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "residual_timeseries.png", dpi=90)
    plt.close(fig)
    files["timeseries"] = "residual_timeseries.png"
    # Per-joint bars.
    res = d.result
    b = np.array(res["gap"]["rms_check_per_joint"])
    a = np.array(res["combined"]["rms_check_per_joint_after"])
    fig, ax = plt.subplots(figsize=(7, 3))
    idx = np.arange(n)
    ax.bar(idx - 0.2, b, 0.4, color="0.6", label="nominal")
    ax.bar(idx + 0.2, a, 0.4, color="tab:blue", label="corrected")
    ax.set_xticks(idx, [f"j{j + 1}" for j in idx])
    ax.set_ylabel("held-out RMS [N·m]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "joint_rms.png", dpi=90)
    plt.close(fig)
    files["bars"] = "joint_rms.png"
    return files


def _fmt(x, digits=3):
    return f"{x:.{digits}g}" if isinstance(x, float) else str(x)


def _params_text(params):
    parts = []
    for k, v in params.items():
        if isinstance(v, list):
            parts.append(f"{k}=[" + ", ".join("-" if x is None else f"{x:.3g}" for x in v) + "]")
        else:
            parts.append(f"{k}={_fmt(v)}")
    return "; ".join(parts)


def write_report(out, diagnosis, model_path, fit_paths, check_paths, plots, wall_time_s, params_file=None):
    res = diagnosis.result
    gap = res["gap"]
    comb = res["combined"]
    n = len(gap["rms_check_per_joint"])
    lines = [
        "# Sim-to-real gap diagnosis", "",
        f"- model: `{model_path}`",
        f"- fit logs: {', '.join(f'`{p}`' for p in fit_paths)}",
        f"- check (held-out) logs: {', '.join(f'`{p}`' for p in check_paths)}",
        f"- residual form: **{gap['residual_form']}** "
        + ("(inverse dynamics with the logged accelerations)" if gap["residual_form"] == "inverse_dynamics"
           else "(momentum form: window-mean torque residual, no differentiated accelerations)"),
        f"- wall time: {wall_time_s:.1f} s", "",
        "## Gap", "",
        f"Held-out RMS residual of the nominal model: **{gap['rms_check']:.3f} N·m** (fit logs: {gap['rms_fit']:.3f} N·m).",
        f"Largest on joints {', '.join(map(str, gap['where']['joints'][:3]))}.", "",
        "| joint | RMS before [N·m] | RMS after [N·m] | reduction |", "|---|---|---|---|",
    ]
    for j in range(n):
        b, a = gap["rms_check_per_joint"][j], comb["rms_check_per_joint_after"][j]
        lines.append(f"| {j + 1} | {b:.3f} | {a:.3f} | {100 * (1 - a / b) if b > 0 else 0:.0f}% |")
    lines += ["", "### Where (share of the squared held-out residual)", "",
              "| regime | share of residual² | share of samples |", "|---|---|---|"]
    for k, v in gap["where"]["regimes"].items():
        lines.append(f"| {k} | {100 * v:.1f}% | {100 * gap['where']['regime_sample_share'][k]:.1f}% |")
    lines += ["", "A regime whose residual share clearly exceeds its sample share is where the model fails.", "",
              "Worst 1-s time windows:", ""]
    for w in gap["where"]["time_windows"]:
        lines.append(f"- `{Path(w['log']).name}` {w['t_start']:.1f}–{w['t_end']:.1f} s: {100 * w['share']:.1f}%")
    if "residual_forms" in gap:
        lines += ["", "Nominal residual RMS by form (per check log): "]
        for log, forms in gap["residual_forms"].items():
            lines.append(f"- `{Path(log).name}`: " + ", ".join(f"{k} {v:.3f}" for k, v in forms.items()))
    sat = gap.get("velocity_saturation")
    if sat and sat["spans"]:
        wo = comb["without_saturated"]
        lines += ["", f"Velocity saturation: joints ran pinned at their top speed on "
                  f"{100 * sat['element_share']:.1f}% of the held-out joint samples, which carry "
                  f"{100 * sat['residual_share']:.1f}% of the nominal residual². There the drive does not "
                  "deliver the logged torque (it swings while velocity and acceleration stay flat), so no "
                  "model of the arm can follow it: these samples are left out of fitting and selection. "
                  f"On the other samples: {wo['rms_check']:.3f} → {wo['rms_check_after']:.3f} N·m "
                  f"({100 * wo['reduction']:.1f}% reduction; all samples {100 * comb['reduction']:.1f}%).", "",
                  "| log | joint | from [s] | to [s] | speed [rad/s] |", "|---|---|---|---|---|"]
        for sp in sat["spans"]:
            lines.append(f"| `{Path(sp['log']).name}` | {sp['joint']} | {sp['t_start']:.2f} | {sp['t_end']:.2f} "
                         f"| {sp['speed_rad_s']:.3f} |")
    lines += ["", "Where the residual left after the combined correction lies (share of its square):", "",
              "| regime | share after | share of samples |", "|---|---|---|"]
    for k, v in comb.get("regimes_after", {}).items():
        lines.append(f"| {k} | {100 * v:.1f}% | {100 * gap['where']['regime_sample_share'][k]:.1f}% |")
    lines += ["", "## Effects", "",
              f"Cause: **{', '.join(res['cause']) if res['cause'] else 'no significant effect'}**", "",
              "| effect | significant | joints | held-out RMS alone [N·m] | reduction alone | parameters |",
              "|---|---|---|---|---|---|"]
    for e in res["effects"]:
        lines.append(f"| {e['name']} | {'yes' if e['significant'] else 'no'} | {', '.join(map(str, e['joints']))} | "
                     f"{e['rms_check_after']:.3f} | {100 * e['reduction']:.1f}% | {_params_text(e['params'])} |")
    lines += ["", "Selection (best set of one or two effects by exhaustive search, then forward-greedy; "
              "each step refits all selected effects on the fit logs and is scored on the check logs):", "",
              "| step | effect | held-out RMS after [N·m] | z (block) | p (block ranks) | relative MSE drop | BIC change |",
              "|---|---|---|---|---|---|---|"]
    for k, s in enumerate(comb["selection"], 1):
        lines.append(f"| {k} | {s['effect']} | {s['rms_check_after']:.3f} | {s['z']:.1f} | {s['p_blocks']:.1e} "
                     f"| {100 * s['relative']:.1f}% | {s['bic_change']:.0f} |")
    rule = res["significance_rule"]
    lines += ["", f"Significance: held-out squared-residual drop > {rule['z_block']} standard errors of its random part "
              f"(block sums over {rule['block_s']} s) or consistent over blocks (Wilcoxon signed-rank of the block "
              f"gains, p ≤ {rule['p_blocks']:.2g}, ≥ {rule['min_blocks']} blocks), > {100 * rule['min_relative']:.0f}% of the current MSE and "
              f"> {100 * rule['min_noise_fraction']:.0f}% of the noise variance (robust, first differences), and BIC on "
              "the fit logs decreases. The final set is ordered by the held-out loss when each effect is left out.", "",
              "## Combined", "",
              f"Effects {', '.join(comb['effects']) or '(none)'}: held-out RMS **{gap['rms_check']:.3f} → "
              f"{comb['rms_check_after']:.3f} N·m** (reduction {100 * comb['reduction']:.1f}%).", ""]
    if any(e["name"] == "time_delay" and e["significant"] and e["params"]["law"].startswith("first-order")
           for e in res["effects"]):
        lines += ["The first-order lag has a state: at each segment start and after each speed-saturated span "
                  "(where its history is unknown) the lagged model restarts from the measured torque.", ""]
    if params_file:
        lines += [f"Corrected model parameters: `{params_file}` (joint-parameter YAML, loadable by "
                  "`load_robot(params_path=...)` / a scenario's `robot.params`; other effects under "
                  "`diagnosed_effects` and `plant_effects`).", ""]
    lines += ["## Plots", ""] + [f"![{k}]({v})" for k, v in plots.items()] + [""]
    Path(out, "report.md").write_text("\n".join(lines))


def write_leave_one_out_report(out, pooled, model_path, fold_dirs):
    """report.md of a leave-one-log-out diagnosis: held-out RMS pooled over the folds per joint
    (all samples and without speed-saturated ones), the mean over folds, each fold, and the
    effects named in every fold."""
    p, u, m = pooled["pooled"], pooled["pooled_unsaturated"], pooled["mean_over_folds"]
    lines = ["# Sim-to-real gap diagnosis, leave one log out", "",
             f"- model: `{model_path}`",
             f"- each of {len(pooled['folds'])} logs held out once, effects fitted on the others "
             "(fold reports linked below)", "",
             "## Held-out RMS pooled over the folds [N·m]", "",
             "| joint | before | after | reduction | before, unsaturated | after, unsaturated | reduction |",
             "|---|---|---|---|---|---|---|"]
    rows = list(zip(p["rms_before_per_joint"], p["rms_after_per_joint"], p["reduction_per_joint"],
                    u["rms_before_per_joint"], u["rms_after_per_joint"], u["reduction_per_joint"]))
    for j, (b, a, r, bu, au, ru) in enumerate(rows, start=1):
        lines.append(f"| {j} | {b:.2f} | {a:.2f} | {100 * r:.1f}% | {bu:.2f} | {au:.2f} | {100 * ru:.1f}% |")
    lines += [f"| all | {p['rms_before']:.2f} | {p['rms_after']:.2f} | **{100 * p['reduction']:.1f}%** "
              f"| {u['rms_before']:.2f} | {u['rms_after']:.2f} | **{100 * u['reduction']:.1f}%** |", "",
              f"Mean over folds (a per-log reduction): {m['rms_before']:.3f} → {m['rms_after']:.3f} N·m "
              f"(**{100 * m['reduction']:.1f}%**). Speed-saturated joint samples (drive at its limit, left out "
              f"of fitting): {100 * pooled['saturated_share']:.1f}%.", "",
              "Effects named in every fold: **" + (", ".join(pooled["named_in_every_fold"]) or "none") + "**; "
              "in some folds only: " + (", ".join(pooled["named_in_some_fold"]) or "none") + ".", "",
              "## Folds", "",
              "| held-out log | before [N·m] | after [N·m] | reduction | unsaturated reduction | cause | report |",
              "|---|---|---|---|---|---|---|"]
    for f, d in zip(pooled["folds"], fold_dirs):
        lines.append(f"| {', '.join(Path(c).name for c in f['check'])} | {f['rms_before']:.3f} | {f['rms_after']:.3f} "
                     f"| {100 * f['reduction']:.1f}% | {100 * f['without_saturated']['reduction']:.1f}% "
                     f"| {', '.join(f['cause']) or 'none'} | [{Path(d).name}]({Path(d).name}/report.md) |")
    Path(out, "report.md").write_text("\n".join(lines + [""]))
