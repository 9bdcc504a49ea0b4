"""The paper's figures from run folders (matplotlib PNG): the 10 intervals vs truth side by side
(Fig. 5), the estimated mass over time (Fig. 6), tracking error and commanded torque per joint
(Figs. 8/9), cond(Y) per plan, and the summary figure of a compare table (Table III)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from safesysid.report import plot_intervals_side_by_side, plt, save_figure, shade_phases

FIG6_METHODS = ("ours", "random", "adap-1", "adap-1-excit")
OUTCOME_COLOURS = {"success": "#9fd89f", "fail": "#f6c36b", "collide": "#ef7d7d", "missing": "#e0e0e0"}


def phases_of(summary: dict) -> list[tuple[str, float, float]]:
    """[(name, t0, t1)] of a run: identification until the task switch (none when the method
    starts with the task), the task until the release, then the settling; a run without a task
    phase is identification throughout."""
    task = summary.get("task")
    if not task:
        return [("identification", 0.0, float(summary["sim_time_s"]))]
    switch, release, end = (float(task[k]) for k in ("switch_time_s", "release_time_s", "end_time_s"))
    phases = [("identification", 0.0, switch)] if switch > 0 else []
    return phases + [("task", switch, release), ("settle", release, end)]


def run_log(folder: Path) -> tuple:
    """(t, tracking error qd - q [rad, wrapped], commanded torque u [N m], log) of a run folder."""
    from safesysid.joint_log import read_joint_log

    log = read_joint_log(Path(folder) / "log.csv")
    n = log.n
    qd = np.column_stack([log.extra[f"qd{k + 1}"] for k in range(n)])
    u = np.column_stack([log.extra[f"u{k + 1}"] for k in range(n)])
    return log.t, np.angle(np.exp(1j * (qd - log.q))), u, log


def plot_joints(
    path: Path,
    series: list[tuple],
    bound: Sequence[float] | None,
    *,
    limit: Sequence[float] | None,
    phases: Sequence[tuple[str, float, float]] = (),
    title: str = "",
) -> Path:
    """Per joint: tracking error (left, with the certified bound) and commanded torque before
    saturation (right, with the limit); series: [(label, t, error, torque)]."""
    n = series[0][2].shape[1]
    fig, axes = plt.subplots(n, 2, figsize=(11, 1.35 * n + 1), sharex=True, squeeze=False)
    for label, t, error, torque in series:
        for j in range(n):
            axes[j, 0].plot(t, error[:, j], lw=0.7, label=label)
            axes[j, 1].plot(t, torque[:, j], lw=0.7, label=label)
    for j in range(n):
        for col, (values, unit) in enumerate(((bound, "e [rad]"), (limit, "u [N m]"))):
            ax = axes[j, col]
            if values is not None:
                ax.axhline(values[j], color="k", ls="--", lw=0.6)
                ax.axhline(-values[j], color="k", ls="--", lw=0.6)
            shade_phases(ax, phases, label=j == 0)
            ax.set_ylabel(f"joint {j + 1}\n{unit}", fontsize=7)
            ax.tick_params(labelsize=7)
    axes[0, 0].set_title("tracking error (dashed: certified bound)", fontsize=9, pad=12)
    axes[0, 1].set_title("commanded torque (dashed: limit)", fontsize=9, pad=12)
    if len(series) > 1:
        axes[0, 1].legend(fontsize=6, ncol=len(series), loc="upper right")
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def plot_conditioning(path: Path, cond_w: list, updates: list[tuple[float, float]], *, title: str = "") -> Path:
    """cond(W) of each accepted plan (the planner's excitation) and cond(Y) after each
    identification update (updates: [(t, cond_Y)])."""
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.2))
    plans = [(k + 1, c) for k, c in enumerate(cond_w) if c is not None and np.isfinite(c)]
    if plans:
        ax1.semilogy(*zip(*plans), "o-")
        ax1.set_xticks([k for k, _ in plans])
    ax1.set_xlabel("plan k")
    ax1.set_ylabel("cond(W) of the plan")
    finite = [(t, c) for t, c in updates if c is not None and np.isfinite(c)]
    if finite:
        ax2.semilogy(*zip(*finite), "s-", color="C1")
    ax2.set_xlabel("t [s] (update)")
    ax2.set_ylabel("cond(Y)")
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def write_run_figures(out: Path, summary: dict, history: list, *, torque_limit: Sequence[float]) -> None:
    """joints.png (Figs. 8/9 for one run, phases shaded) and conditioning.png (cond per plan)."""
    out = Path(out)
    t, error, u, _ = run_log(out)
    title = f"{summary['scenario']} / {summary['method']} ({summary['payload_true'].get('dumbbell')})"
    bound = summary.get("tracking_bound_per_joint_rad")
    plot_joints(
        out / "joints.png",
        [(summary["method"], t, error, u)],
        bound,
        limit=torque_limit,
        phases=phases_of(summary),
        title=title,
    )
    cond_w = summary["planner"].get("cond_W") or []
    plot_conditioning(out / "conditioning.png", cond_w, [(h["t"], h.get("cond_Y")) for h in history], title=title)


# ---- compare ------------------------------------------------------------------------------------
def _first_runs(done, dumbbell):
    """{method: summary} of trial 0 (else the lowest trial) of each method with that dumbbell."""
    chosen = {}
    for s in sorted(done, key=lambda s: s["trial"]):
        if s["dumbbell"] == dumbbell:
            chosen.setdefault(s["method"], s)
    return chosen


def plot_mass_over_time(path: Path, series: dict, truth_kg: float, *, title: str = "") -> Path:
    """Fig. 6: each method's estimated end-effector mass over time (series: {method: (t, m,
    switch_time_s or None)}), the task switch dotted, the truth dashed."""
    fig, ax = plt.subplots(figsize=(9, 3.6))
    for i, (method, (t, m, switch)) in enumerate(series.items()):
        ax.plot(t, m, lw=1.2, color=f"C{i}", label=method)
        if switch:
            ax.axvline(switch, color=f"C{i}", ls=":", lw=0.8)
    ax.axhline(truth_kg, color="r", ls="--", lw=0.8, label="truth")
    ax.set_xlabel("t [s]  (dotted: start of the task phase)")
    ax.set_ylabel("estimated mass [kg]")
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=10)
    return save_figure(fig, path)


def _task_window(summary, t):
    phases = dict((name, (t0, t1)) for name, t0, t1 in phases_of(summary))
    t0, t1 = phases.get("task", (t[0], t[-1]))
    return (t >= t0) & (t <= t1), t0


def compare_figures(out: Path, done: list[dict], torque_limit: Sequence[float] | None = None) -> list[Path]:
    """Fig. 5 (ours and random), Fig. 6 (ours, random, adap-1, adap-1-excit: those present) for
    the lightest dumbbell's first trial, and Figs. 8/9 per method (task phase, one line per
    dumbbell; time from the task's start). Methods absent from the compare are skipped."""
    out = Path(out)
    if not done:
        return []
    by_mass = sorted(
        {s["dumbbell"] for s in done},
        key=lambda d: min(s["payload_true"]["theta"][0] for s in done if s["dumbbell"] == d),
    )
    lightest = by_mass[0]
    first = _first_runs(done, lightest)
    written = []
    scenario = done[0]["scenario"]
    truth = first[next(iter(first))]["payload_true"]["theta"]
    pair = {m: first[m] for m in ("ours", "random") if m in first}
    if pair:
        estimates = {
            m: (s["estimate"]["nominal"], s["estimate"]["lower"], s["estimate"]["upper"]) for m, s in pair.items()
        }
        title = f"{scenario}, {lightest}: intervals after identification (Fig. 5)"
        written.append(plot_intervals_side_by_side(out / "fig5_intervals.png", estimates, truth, title=title))
    series = {}
    for m in FIG6_METHODS:
        if m in first:
            t, _, _, log = run_log(out / first[m]["folder"])
            task = first[m].get("task")
            if "est_m" in log.extra:  # the estimate in force at each sample (log.csv of `safesysid run`)
                series[m] = (t, log.extra["est_m"], task["switch_time_s"] if task else None)
    if series:
        title = f"{scenario}, {lightest}: estimated end-effector mass (Fig. 6)"
        written.append(plot_mass_over_time(out / "fig6_mass.png", series, truth[0], title=title))
    for m in dict.fromkeys(s["method"] for s in done):
        lines, bound = [], None
        for d in by_mass:
            s = _first_runs(done, d).get(m)
            if s is None:
                continue
            t, error, u, _ = run_log(out / s["folder"])
            window, t0 = _task_window(s, t)
            lines.append((d, t[window] - t0, error[window], u[window]))
            bound = bound or s["tracking_bound_per_joint_rad"]
        if lines:
            title = f"{scenario} / {m}: task phase (time from its start), first trial per dumbbell (Figs. 8/9)"
            written.append(
                plot_joints(out / f"fig8_task_{m}.png", lines, bound, limit=torque_limit, phases=(), title=title)
            )
    return written


def table_figure(path: Path, scenario_name: str, rows: dict, *, dumbbells: list[str]) -> Path:
    """The compare table as a picture: per method and dumbbell the share of successful runs,
    coloured by outcome (green all succeeded, orange a failure, red a collision), and the
    Table III cell."""
    methods = list(rows)
    fig, ax = plt.subplots(figsize=(1.3 * len(dumbbells) + 4.5, 0.42 * len(methods) + 1.4))
    ax.set_xlim(0, len(dumbbells) + 2.4)
    ax.set_ylim(len(methods), -1)
    ax.axis("off")
    for j, d in enumerate(dumbbells):
        ax.text(j + 0.5, -0.5, d, ha="center", va="center", fontsize=9, weight="bold")
    ax.text(len(dumbbells) + 1.2, -0.5, scenario_name, ha="center", va="center", fontsize=9, weight="bold")
    for i, m in enumerate(methods):
        ax.text(-0.05, i + 0.5, m, ha="right", va="center", fontsize=9)
        for j, d in enumerate(dumbbells):
            entry = rows[m]["per_dumbbell"][d]
            outcome = "missing" if entry["runs"] == 0 else "success" if entry["success"] == entry["runs"] else "fail"
            if "collision" in entry["failures"]:
                outcome = "collide"
            ax.add_patch(plt.Rectangle((j + 0.04, i + 0.06), 0.92, 0.88, color=OUTCOME_COLOURS[outcome]))
            ax.text(j + 0.5, i + 0.5, f"{entry['success']}/{entry['runs']}", ha="center", va="center", fontsize=8)
        cell = rows[m]["cell"]
        colour = OUTCOME_COLOURS["collide" if cell == "collide" else "success" if cell == "success" else "fail"]
        ax.add_patch(plt.Rectangle((len(dumbbells) + 0.1, i + 0.06), 2.2, 0.88, color=colour))
        ax.text(len(dumbbells) + 1.2, i + 0.5, cell, ha="center", va="center", fontsize=8, weight="bold")
    ax.set_title("successful runs / runs per dumbbell; Table III cell", fontsize=9)
    return save_figure(fig, path)
