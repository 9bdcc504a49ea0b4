"""report.md and report.html of a gap diagnosis (plots: diagnose_plots.py; HTML: report_html.py)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from safesysid.systems.diagnosis.report_data import unresolved_text

from .diagnose_plots import joint_bars, residual_map_plot
from .report_html import write_html

if TYPE_CHECKING:
    from safesysid.systems.diagnosis import Diagnosis


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


# ---- the verdict: where, why (with values and units), how much it shrinks on held-out logs --
def _joint_list(joints):
    """[1, 2, 3, 5] -> '1–3, 5'."""
    out, run = [], []
    for j in sorted(joints) + [None]:
        if run and (j is None or j != run[-1] + 1):
            out.append(f"{run[0]}–{run[-1]}" if len(run) > 2 else ", ".join(map(str, run)))
            run = []
        if j is not None:
            run.append(j)
    return ", ".join(out)


def _per_joint(values, joints, unit):
    vals = [values[j - 1] for j in joints if values[j - 1] is not None]
    if not vals:
        return ""
    if len(joints) <= 3:
        return ", ".join(f"{v:.3g}" + f" (joint {j})" for j, v in zip(joints, vals)) + f" {unit}".rstrip()
    return f"{min(vals):.3g}–{max(vals):.3g} {unit} on joints {_joint_list(joints)}".replace("  ", " ")


def effect_text(entry: dict) -> str:
    """One effect with its fitted values and units, as a user reads it."""
    name, p, joints = entry["name"], entry["params"], entry["joints"]
    if name == "coulomb_friction":
        return "Coulomb friction Fc " + _per_joint(p["Fc_Nm"], joints, "N·m")
    if name == "viscous_friction":
        return "viscous friction Fv " + _per_joint(p["Fv_Nms_rad"], joints, "N·m·s/rad")
    if name == "stribeck_friction":
        return f"Stribeck friction (vs {p['vs_rad_s']:.3g} rad/s) Fs " + _per_joint(p["Fs_Nm"], joints, "N·m")
    if name == "load_friction":
        return "load-dependent friction μ " + _per_joint(p["mu"], joints, "(N·m per N·m)")
    if name == "armature":
        return "armature Ia " + _per_joint(p["Ia_kgm2"], joints, "kg·m²")
    if name == "torque_offset":
        return "torque offset " + _per_joint(p["offset_Nm"], joints, "N·m")
    if name == "torque_scale":
        return "torque scale " + _per_joint(p["scale"], joints, "")
    if name == "payload":
        return (
            f"payload {p['mass_kg']:.3g} kg at CoM ["
            + ", ".join(f"{x:.3f}" for x in p["com_m"])
            + "] m (end-effector frame)"
        )
    if name == "time_delay":
        d = p["delay_s"]
        if p.get("time_law") == "lag" or p["law"].startswith("first-order"):
            return f"first-order lag of the torque signal, time constant {1000 * d:.1f} ms"
        kind = "measurement lags the motion" if d > 0 else "torque leads the motion (actuation delay)"
        return f"pure delay {1000 * abs(d):.1f} ms ({kind})"
    if name == "base_tilt":
        return f"base tilt roll {p['roll_rad']:.4f} rad, pitch {p['pitch_rad']:.4f} rad"
    if name == "joint_elasticity":
        return "joint stiffness k " + _per_joint(p["stiffness_Nm_rad"], joints, "N·m/rad")
    return f"{name} ({_params_text(p)})"


def _regime_text(gap):
    """Regimes holding clearly more of the residual² than of the samples, worst first."""
    share, samples = gap["where"]["regimes"], gap["where"]["regime_sample_share"]
    excess = sorted(
        ((share[k] - samples[k], k) for k in share if samples[k] > 0 and share[k] > 1.2 * samples[k]), reverse=True
    )[:2]
    return [
        f"{k.replace('_', ' ')} ({100 * share[k]:.0f} % of the residual² on {100 * samples[k]:.0f} % of the samples)"
        for _, k in excess
    ]


def verdict_lines(result: dict, frozen: bool = False) -> list[str]:
    """The three lines report.md opens with: where the model fails, the effects that explain
    it with fitted values and units, and the shrinkage on held-out (test) logs."""
    gap, test = result["gap"], result["test"]
    per_joint = gap["rms_check_per_joint"]
    worst = gap["where"]["joints"][:3]
    regimes = _regime_text(gap)
    where = (
        "**Where:** the model fails most on joint"
        + ("s " if len(worst) > 1 else " ")
        + ", ".join(f"{j} ({per_joint[j - 1]:.2f} N·m RMS)" for j in worst)
        + f" of {len(per_joint)} (all joints {gap['rms_check']:.2f} N·m)"
        + (
            "; the residual concentrates at " + " and ".join(regimes)
            if regimes
            else "; spread over the motion (no regime stands out)"
        )
        + "."
    )
    named = [e for e in result["effects"] if e["significant"]]
    if named:
        why = (
            "**Why:** "
            + "; ".join(effect_text(e) for e in named)
            + (
                " (the frozen corrected model, nothing fitted)."
                if frozen
                else " (selected on the fit logs only, inner cross-validation)."
            )
        )
    elif result.get("unresolved"):
        why = "**Why:** no effect is named."
    else:
        why = "**Why:** no effect of the vocabulary explains a significant part of it on the fit logs."
    why += unresolved_text(result)
    logs = ", ".join(f"`{Path(p).name}`" for p in test["logs"])
    wo = test["without_saturated"]
    change = (
        f"**{100 * test['reduction']:.1f} % less**"
        if test["rms_after"] <= test["rms_before"]
        else f"**{100 * (test['rms_after'] / test['rms_before'] - 1):.1f} % more**: the correction does not "
        "carry over to these logs"
    )
    shrink = (
        f"**Held-out (test):** RMS {test['rms_before']:.3f} → {test['rms_after']:.3f} N·m "
        f"({change}) on {logs}, "
        + ("scored with the frozen model, nothing fitted" if frozen else "never used by any selection step")
        + (
            f"; without speed-saturated samples {100 * wo['reduction']:.1f} %"
            if gap["velocity_saturation"]["spans"]
            else ""
        )
        + (
            f"; inner cross-validation on the fit logs {100 * result['cross_validation']['reduction']:.1f} %."
            if "cross_validation" in result
            else "."
        )
    )
    return [where, why, shrink]


def _inputs_lines(gap: dict, model_path, fit_paths, check_paths, *, wall_time_s: float, frozen: bool) -> list[str]:
    return [
        "## Inputs",
        "",
        f"- model: `{model_path}`",
        (
            "- frozen corrected model: nothing fitted, no selection made"
            if frozen
            else f"- fit logs (all selection and fitting): {', '.join(f'`{p}`' for p in fit_paths)}"
        ),
        f"- check logs (scored once, `test`): {', '.join(f'`{p}`' for p in check_paths)}",
        f"- residual form: **{gap['residual_form']}** "
        + (
            "(inverse dynamics with the logged accelerations)"
            if gap["residual_form"] == "inverse_dynamics"
            else "(momentum form: window-mean torque residual, no differentiated accelerations)"
        ),
        f"- wall time: {wall_time_s:.1f} s",
        "",
    ]


def _gap_lines(gap: dict, comb: dict) -> list[str]:
    """The held-out gap per joint, where it lies (regimes, worst windows) and by residual form."""
    lines = [
        "## Gap on the check logs (test)",
        "",
        f"Held-out RMS residual of the nominal model: **{gap['rms_check']:.3f} N·m**"
        + (f" (fit logs: {gap['rms_fit']:.3f} N·m)." if gap.get("rms_fit") is not None else "."),
        f"Largest on joints {', '.join(map(str, gap['where']['joints'][:3]))}.",
        "",
        "| joint | RMS before [N·m] | RMS after [N·m] | reduction |",
        "|---|---|---|---|",
    ]
    for j in range(len(gap["rms_check_per_joint"])):
        b, a = gap["rms_check_per_joint"][j], comb["rms_check_per_joint_after"][j]
        lines.append(f"| {j + 1} | {b:.3f} | {a:.3f} | {100 * (1 - a / b) if b > 0 else 0:.0f}% |")
    lines += [
        "",
        "### Where (share of the squared held-out residual)",
        "",
        "| regime | share of residual² | share of samples |",
        "|---|---|---|",
    ]
    for k, v in gap["where"]["regimes"].items():
        lines.append(f"| {k} | {100 * v:.1f}% | {100 * gap['where']['regime_sample_share'][k]:.1f}% |")
    lines += [
        "",
        "A regime whose residual share clearly exceeds its sample share is where the model fails.",
        "",
        "Worst 1-s time windows:",
        "",
    ]
    for w in gap["where"]["time_windows"]:
        lines.append(f"- `{Path(w['log']).name}` {w['t_start']:.1f}–{w['t_end']:.1f} s: {100 * w['share']:.1f}%")
    if "residual_forms" in gap:
        lines += ["", "Nominal residual RMS by form (per check log): ", ""]
        for log, forms in gap["residual_forms"].items():
            lines.append(f"- `{Path(log).name}`: " + ", ".join(f"{k} {v:.3f}" for k, v in forms.items()))
    return lines


def _saturation_lines(gap: dict, comb: dict) -> list[str]:
    """The velocity-saturated spans left out of fitting and selection (none: no lines)."""
    sat = gap.get("velocity_saturation")
    if not (sat and sat["spans"]):
        return []
    wo = comb["without_saturated"]
    lines = [
        "",
        f"Velocity saturation: joints ran pinned at their top speed on "
        f"{100 * sat['element_share']:.1f}% of the held-out joint samples, which carry "
        f"{100 * sat['residual_share']:.1f}% of the nominal residual². There the drive does not "
        "deliver the logged torque (it swings while velocity and acceleration stay flat), so no "
        "model of the arm can follow it: these samples are left out of fitting and selection "
        "(the top speeds are those of the fit logs, frozen in corrected_model.yaml). "
        f"On the other samples: {wo['rms_check']:.3f} → {wo['rms_check_after']:.3f} N·m "
        f"({100 * wo['reduction']:.1f}% reduction; all samples {100 * comb['reduction']:.1f}%).",
        "",
        "| log | joint | from [s] | to [s] | speed [rad/s] |",
        "|---|---|---|---|---|",
    ]
    for sp in sat["spans"]:
        lines.append(
            f"| `{Path(sp['log']).name}` | {sp['joint']} | {sp['t_start']:.2f} | {sp['t_end']:.2f} "
            f"| {sp['speed_rad_s']:.3f} |"
        )
    return lines


def _combined_lines(res: dict, params_file: str | None) -> list[str]:
    """The combined correction, the lag's restarts (when selected) and the corrected model's files."""
    gap, comb = res["gap"], res["combined"]
    lines = [
        "## Combined",
        "",
        f"Effects {', '.join(comb['effects']) or '(none)'}: held-out (test) RMS **{gap['rms_check']:.3f} → "
        f"{comb['rms_check_after']:.3f} N·m** (reduction {100 * comb['reduction']:.1f}%).",
        "",
    ]
    if any(
        e["name"] == "time_delay" and e["significant"] and e["params"]["law"].startswith("first-order")
        for e in res["effects"]
    ):
        lines += [
            "The first-order lag has a state: at each segment start and after each speed-saturated span "
            "(where its history is unknown) the lagged model restarts from the measured torque.",
            "",
        ]
    if params_file:
        lines += [
            "Corrected model: `corrected_model.yaml` (the starting model, every selected effect with its "
            "parameters and the frozen scoring rule); score it on new logs with `safesysid diagnose --model "
            "corrected_model.yaml --check NEW.csv` (fits nothing). "
            f"Joint parameters alone: `{params_file}` (joint-parameter YAML, loadable by "
            "`load_robot(params_path=...)` / a scenario's `robot.params`).",
            "",
        ]
    return lines


def write_report(
    out: str | Path,
    diagnosis: Diagnosis,
    model_path: str | Path,
    *,
    fit_paths: Sequence[str | Path],
    check_paths: Sequence[str | Path],
    plots: dict[str, str],
    wall_time_s: float,
    params_file: str | None = None,
    frozen: bool = False,
) -> None:
    """report.md (verdict first, then tables and plots) and report.html (the same, plots embedded)."""
    res = diagnosis.result
    gap, comb = res["gap"], res["combined"]
    title = "Sim-to-real gap: frozen corrected model scored" if frozen else "Sim-to-real gap diagnosis"
    lines = [f"# {title}", ""]
    for v in verdict_lines(res, frozen):
        lines += [v, ""]
    lines += _inputs_lines(gap, model_path, fit_paths, check_paths, wall_time_s=wall_time_s, frozen=frozen)
    lines += _gap_lines(gap, comb) + _saturation_lines(gap, comb)
    lines += [
        "",
        "Where the residual left after the correction lies (share of its square):",
        "",
        "| regime | share after | share of samples |",
        "|---|---|---|",
    ]
    for k, v in comb.get("regimes_after", {}).items():
        lines.append(f"| {k} | {100 * v:.1f}% | {100 * gap['where']['regime_sample_share'][k]:.1f}% |")
    lines += residual_map_lines(comb.get("residual_map_after"))
    lines += _effects_section(res, frozen)
    lines += _combined_lines(res, params_file)
    lines += ["## Plots", ""] + [f"![{k}]({v})" for k, v in plots.items()] + [""]
    text = "\n".join(lines)
    Path(out, "report.md").write_text(text)
    write_html(Path(out, "report.html"), text, out, title=title)


def residual_map_lines(residual_map: dict | None) -> list[str]:
    """The residual map (report_data.residual_map) as a table: per joint, its share of the
    residual² left and the regimes and joint-angle bins where it concentrates (ratio >= 1.5)."""
    if not residual_map:
        return []
    lines = [
        "",
        "Residual map after the correction (plot `residual_map.png`): per joint, its share of the residual² "
        "left, and where it concentrates (share of the joint's residual² / share of its samples, >= 1.5):",
        "",
        "| joint | RMS after [N·m] | share | concentrates in |",
        "|---|---|---|---|",
    ]
    for j in residual_map["joints"]:
        spots = [(k, c["share"] / c["samples"]) for k, c in j["regimes"].items() if c["samples"] > 0]
        spots += [
            (f"angle {b['q_from_rad']:.2f}..{b['q_to_rad']:.2f} rad", b["share"] / b["samples"])
            for b in j["pose_bins"]
            if b["samples"] > 0
        ]
        hot = ", ".join(f"{k} ×{r:.1f}" for k, r in sorted(spots, key=lambda x: -x[1]) if r >= 1.5) or "-"
        lines.append(f"| {j['joint']} | {j['rms']:.3f} | {100 * j['share']:.1f}% | {hot} |")
    return lines


def _effects_section(res, frozen):
    if frozen:
        lines = [
            "",
            "## Effects (frozen)",
            "",
            "| effect | joints | test RMS with this effect alone [N·m] | reduction alone | parameters |",
            "|---|---|---|---|---|",
        ]
        for e in res["effects"]:
            lines.append(
                f"| {e['name']} | {', '.join(map(str, e['joints']))} | {e['rms_check_after']:.3f} "
                f"| {100 * e['reduction']:.1f}% | {_params_text(e['params'])} |"
            )
        return lines + [""]
    cv = res["cross_validation"]
    lines = [
        "",
        "## Effects",
        "",
        f"Cause: **{', '.join(res['cause']) if res['cause'] else 'no significant effect'}**",
        "",
        "| effect | significant | joints | test RMS alone [N·m] | test reduction alone | parameters |",
        "|---|---|---|---|---|---|",
    ]
    for e in res["effects"]:
        lines.append(
            f"| {e['name']} | {'yes' if e['significant'] else 'no'} | {', '.join(map(str, e['joints']))} | "
            f"{e['rms_check_after']:.3f} | {100 * e['reduction']:.1f}% | {_params_text(e['params'])} |"
        )
    lines += [
        "",
        f"Selection on the fit logs only ({cv['scheme'].replace('_', ' ')}; "
        "the validation residuals of the inner folds, each fit-log sample validated once): "
        "best set of one or two effects by exhaustive search, then forward-greedy.",
        "",
        "| fold | fit on | validated on |",
        "|---|---|---|",
    ]
    for k, f in enumerate(cv["folds"], 1):
        lines.append(
            f"| {k} | {', '.join(f'`{Path(p).name}`' for p in f['fit'])} "
            f"| {', '.join(f'`{Path(p).name}`' for p in f['validate'])} |"
        )
    lines += [
        "",
        "| step | effect | validation RMS after [N·m] | z (block) | p (block ranks) | relative MSE drop | BIC change |",
        "|---|---|---|---|---|---|---|",
    ]
    for k, s in enumerate(cv["selection"], 1):
        lines.append(
            f"| {k} | {s['effect']} | {s['rms_after']:.3f} | {s['z']:.1f} | {s['p_blocks']:.1e} "
            f"| {100 * s['relative']:.1f}% | {s['bic_change']:.0f} |"
        )
    rule = res["significance_rule"]
    lines += [
        "",
        f"Cross-validation (`cross_validation`): {cv['rms_before']:.3f} → {cv['rms_after']:.3f} N·m "
        f"({100 * cv['reduction']:.1f}%); test (`test`, the check logs): {res['test']['rms_before']:.3f} → "
        f"{res['test']['rms_after']:.3f} N·m ({100 * res['test']['reduction']:.1f}%).",
        "",
        f"Significance (on validation residuals): squared-residual drop > {rule['z_block']} standard errors "
        f"of its random part (block sums over {rule['block_s']} s) or consistent over blocks (Wilcoxon "
        f"signed-rank of the block gains, p ≤ {rule['p_blocks']:.2g}, ≥ {rule['min_blocks']} blocks), "
        f"> {100 * rule['min_relative']:.0f}% of the current MSE and > {100 * rule['min_noise_fraction']:.0f}% "
        "of the noise variance (robust, first differences), and BIC on the inner training folds decreases. "
        "The final set is ordered by the validation loss when each effect is left out; its parameters are "
        "then refitted on all fit logs and the check logs are scored once.",
        "",
    ]
    return lines


def write_leave_one_out_report(
    out: str | Path, pooled: dict, model_path: str | Path, *, fold_dirs: Sequence[Path]
) -> None:
    """report.md/.html of a nested leave-one-log-out diagnosis: test RMS pooled over the folds per
    joint (all samples and without speed-saturated ones), the mean over folds, each fold, and the
    effects named in every fold."""
    p, u, m = pooled["pooled"], pooled["pooled_unsaturated"], pooled["mean_over_folds"]
    named = ", ".join(pooled["named_in_every_fold"]) or "none"
    lines = [
        "# Sim-to-real gap diagnosis, leave one log out (nested)",
        "",
        f"**Held-out (test):** pooled over {len(pooled['folds'])} folds RMS {p['rms_before']:.2f} → "
        f"{p['rms_after']:.2f} N·m (**{100 * p['reduction']:.1f} % less**; without speed-saturated samples "
        f"{100 * u['reduction']:.1f} %); effects named in every fold: **{named}**.",
        "",
        f"- model: `{model_path}`",
        f"- each of {len(pooled['folds'])} logs held out once; selection on inner folds of the other logs "
        "only (leave one of them out), parameters refitted on them, the held-out log scored once "
        "(fold reports linked below)",
        "",
        "## Held-out RMS pooled over the folds [N·m]",
        "",
        "| joint | before | after | reduction | before, unsaturated | after, unsaturated | reduction |",
        "|---|---|---|---|---|---|---|",
    ]
    rows = list(
        zip(
            p["rms_before_per_joint"],
            p["rms_after_per_joint"],
            p["reduction_per_joint"],
            u["rms_before_per_joint"],
            u["rms_after_per_joint"],
            u["reduction_per_joint"],
        )
    )
    for j, (b, a, r, bu, au, ru) in enumerate(rows, start=1):
        lines.append(f"| {j} | {b:.2f} | {a:.2f} | {100 * r:.1f}% | {bu:.2f} | {au:.2f} | {100 * ru:.1f}% |")
    lines += [
        f"| all | {p['rms_before']:.2f} | {p['rms_after']:.2f} | **{100 * p['reduction']:.1f}%** "
        f"| {u['rms_before']:.2f} | {u['rms_after']:.2f} | **{100 * u['reduction']:.1f}%** |",
        "",
        f"Mean over folds (a per-log reduction): {m['rms_before']:.3f} → {m['rms_after']:.3f} N·m "
        f"(**{100 * m['reduction']:.1f}%**). Speed-saturated joint samples (drive at its limit, left out "
        f"of fitting): {100 * pooled['saturated_share']:.1f}%.",
        "",
        f"Effects named in every fold: **{named}**; in some folds only: "
        + (", ".join(pooled["named_in_some_fold"]) or "none")
        + ".",
        "",
        "## Folds",
        "",
        "| held-out log | before [N·m] | after [N·m] | test reduction | unsaturated | inner CV reduction "
        "| cause | report |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for f, d in zip(pooled["folds"], fold_dirs):
        lines.append(
            f"| {', '.join(Path(c).name for c in f['check'])} | {f['rms_before']:.3f} | {f['rms_after']:.3f} "
            f"| {100 * f['reduction']:.1f}% | {100 * f['without_saturated']['reduction']:.1f}% "
            f"| {100 * f['cross_validation']['reduction']:.1f}% "
            f"| {', '.join(f['cause']) or 'none'} | [{Path(d).name}]({Path(d).name}/report.md) |"
        )
    bars = joint_bars(
        Path(out) / "pooled_joint_rms.png",
        p["rms_before_per_joint"],
        p["rms_after_per_joint"],
        label_after="corrected (each log held out once)",
    )
    plots = [f"![pooled per joint]({bars})"]
    if pooled.get("residual_map_after"):
        lines += ["", "## Where the held-out residual left lies (pooled over the folds)"]
        lines += residual_map_lines(pooled["residual_map_after"])
        plots.append(
            f"![residual map]({residual_map_plot(Path(out) / 'residual_map.png', pooled['residual_map_after'])})"
        )
    lines += ["", "## Plots", "", *plots, ""]
    text = "\n".join(lines)
    Path(out, "report.md").write_text(text)
    write_html(Path(out, "report.html"), text, out, title="Gap diagnosis, leave one log out")
