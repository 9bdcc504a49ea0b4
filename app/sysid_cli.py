"""`safesysid sysid LOG.csv --scenario S.yaml [--model corrected_model.yaml] --out DIR`: Algorithm 1
offline on a joint log (a CSV or a ROS bag, see app/joint_bag.py).

With --model (a corrected_model.yaml of `safesysid diagnose`) the estimator's robot model is
the diagnosis' starting model with its corrected friction, armature and torque offset, and a
diagnosed first-order lag of the torque signal (tau_meas + d dtau_meas/dt = tau) is undone in
the integral form the estimator works in (a diagnosed pure delay instead re-pairs each step with
its reading, estimator.torque_delay_s, exactly): over a segment [a, b],
    int tau dt = int tau_meas dt + d (tau_meas(b) - tau_meas(a)),
exact for the lag law (the model side equivalent: nothing is differentiated). The noise of the
two endpoint readings enters multiplied by d, so each row's error term gains d (r_a + r_b), r
the declared per-sample bound: the interval stays an enclosure under the declared noise bound
of the signal fed in (the logged one). Effects the estimator's model has no term for (load or
Stribeck friction, torque scale, base tilt, elasticity) are listed as not applied.

The log is replayed as Algorithm 2 sees it online: the estimator gets the data chunk by chunk
and updates every planner.replan_period_s (intervals intersected from the scenario's
initial_interval on). Writes DIR/estimate.json and DIR/intervals.png (each of the 10 intervals
with θ0, the prior nominal and the truth when the scenario names the payload, like the paper's
Fig. 5) and DIR/history.png (the intervals over the updates).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
from safesysid.cli import BadInput
from safesysid.joint_bag import read_log
from safesysid.scenario import check_starting_scenario, load_scenario
from safesysid.systems.config import Scenario, ScenarioError
from safesysid.systems.estimation import (
    EstimatorError,
    EstimatorSettings,
    IncrementalEstimator,
    SegmentRows,
    torque_radius,
)
from safesysid.systems.estimation.settings import EPS, lag_interval
from safesysid.systems.model import inertial
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.loading import resolve_path, robot_from_scenario, scenario_dir
from safesysid.systems.model.robot_model import RobotModel


def payload_truth(scenario: Scenario, robot: RobotModel) -> np.ndarray | None:
    """θ_e of the end effector + the scenario's dumbbell, or None when it names none."""
    from safesysid.systems.model.payload import load_dumbbells, payload_theta_in_end_effector

    name = scenario.payload.dumbbell
    if name == "none":
        return None
    path = resolve_path(scenario.payload.dumbbells_file, scenario_dir(scenario))
    dumbbells = load_dumbbells(path)
    if name not in dumbbells:
        raise ScenarioError(f"{scenario.source}: payload.dumbbell: {name!r} is not in {path} ({', '.join(dumbbells)})")
    return robot.theta_e + payload_theta_in_end_effector(dumbbells[name], robot.extra["grasp_point"])


def undo_torque_lag(
    rows: SegmentRows, tau_meas: np.ndarray, lag_s: float | list[float], *, settings: EstimatorSettings, first: int = 0
) -> None:
    """Rows `first`.. of the estimator's segments (SegmentRows, indices into tau_meas) for a
    torque signal logged through a first-order lag d: int tau = int tau_meas + d (tau_meas(b) -
    tau_meas(a)), the endpoint noise bounded by d (r_a + r_b) in the row's error term. A lag
    d in [lo, hi]: the midpoint's correction, and the error term gains the half-width times
    |tau_meas(b) - tau_meas(a)| (the correction is linear in d) and takes hi for the noise."""
    lo, hi = lag_interval(lag_s)
    mid, half = (lo, 0.0) if lo == hi else (0.5 * (lo + hi), 0.5 * (hi - lo) + EPS * hi)  # outward
    a, b = rows.start_index[first:], rows.end_index[first:]
    r = torque_radius(tau_meas, settings)
    step = tau_meas[b] - tau_meas[a]
    rows.T[first:] += mid * step
    rows.quad[first:] += hi * (r[a] + r[b]) + half * np.abs(step)


def run_sysid(
    log: JointLog,
    robot: RobotModel,
    settings: EstimatorSettings,
    *,
    period_s: float,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
    prior_nominal: np.ndarray | None = None,
    torque_lag_s: float | list[float] = 0.0,
) -> tuple[IncrementalEstimator, list[dict]]:
    """Replay a JointLog through the incremental estimator; returns (estimator, history)."""
    est = IncrementalEstimator(robot, settings=settings, prior=prior, prior_nominal=prior_nominal)
    history = []
    t = log.t
    edges = list(np.arange(t[0] + period_s, t[-1], period_s)) + [t[-1]]
    start = 0
    for edge in edges:
        stop = int(np.searchsorted(t, edge, side="right"))
        if stop > start:
            done = len(est.rows)
            est.add(t[start:stop], log.q[start:stop], log.v[start:stop], log.tau[start:stop])
            if np.any(torque_lag_s):
                undo_torque_lag(est.rows, log.tau, torque_lag_s, settings=settings, first=done)
            start = stop
        try:
            e = est.update()
        except EstimatorError:
            continue  # not one segment yet: wait for more data
        history.append(
            {
                "t": float(t[stop - 1]),
                "nominal": e.theta_e.tolist(),
                "lower": e.lower.tolist(),
                "upper": e.upper.tolist(),
                "case": e.case,
                "consistent": e.consistent,
                "cond_Y": float(e.cond_Y),
                "update_time_s": e.update_time_s,
                "message": e.message,
            }
        )
    return est, history


def plot_intervals(
    path: str | Path, est: IncrementalEstimator, prior_nominal: np.ndarray, *, truth: np.ndarray | None, title: str
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 5, figsize=(14, 5.5))
    for k, ax in enumerate(axes.ravel()):
        lo, hi, nom = est.lower[k], est.upper[k], est.theta_e[k]
        ax.fill_between([-0.3, 0.3], [lo, lo], [hi, hi], color="tab:blue", alpha=0.25, label="[θ_e]")
        ax.plot([0], [nom], "o", color="tab:blue", label="θ0 (estimate)")
        ax.plot([0.15], [prior_nominal[k]], "s", color="gray", label="prior nominal")
        if truth is not None:
            ax.plot([-0.15], [truth[k]], "r*", ms=11, label="truth")
        ax.set_xlim(-0.5, 0.5)
        ax.set_xticks([])
        ax.set_title(f"{inertial.NAMES[k]} [{inertial.UNITS[k]}]", fontsize=9)
        ax.tick_params(labelsize=8)
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_history(path: str | Path, history: list[dict], truth: np.ndarray | None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    times = np.array([h["t"] for h in history])
    lo, hi, nom = (np.array([h[k] for h in history]) for k in ("lower", "upper", "nominal"))
    fig, axes = plt.subplots(2, 5, figsize=(14, 5.5), sharex=True)
    for k, ax in enumerate(axes.ravel()):
        ax.fill_between(times, lo[:, k], hi[:, k], step="post", alpha=0.3)
        ax.step(times, nom[:, k], where="post")
        if truth is not None:
            ax.axhline(truth[k], color="r", ls="--", lw=0.8)
        ax.set_title(f"{inertial.NAMES[k]} [{inertial.UNITS[k]}]", fontsize=9)
        ax.tick_params(labelsize=8)
    for ax in axes[1]:
        ax.set_xlabel("t [s]", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def corrected_model(path: str | Path) -> tuple[RobotModel, float, float, dict]:
    """(robot, torque lag [s], torque shift [s] (estimator.torque_delay_s), corrections summary) of
    a corrected_model.yaml for the estimator."""
    from safesysid.systems.model import corrections as mc
    from safesysid.systems.model.loading import starting_robot

    try:
        corr = mc.read_correction(path)
        check_starting_scenario(corr)
        robot = mc.corrected_robot(starting_robot(corr), corr)
        lag, shift = mc.torque_lag_s(corr), mc.torque_shift_s(corr)
    except mc.CorrectionError as err:
        raise BadInput(f"--model: {err}") from err
    applied = [e.name for e in corr.effects if e.name in mc.ROBOT_SIDE or (e.name == "time_delay" and (lag or shift))]
    summary = {
        "file": str(Path(path).resolve()),
        "starting_model": str(corr.model_path()),
        "applied": applied,
        "torque_lag_s": lag,
        "torque_delay_s": shift,
        "not_applied": [e.name for e in corr.effects if e.name not in applied],
    }
    return robot, lag, shift, summary


def _settings_record(settings: EstimatorSettings) -> dict:
    """estimate.json's settings; the declared bound also under its earlier keys (readers rely on them)."""
    noise = settings.declared_noise
    return {**dataclasses.asdict(settings), "torque_ratio": noise.ratio, "torque_floor_Nm": noise.floor_Nm}


def _sysid_settings(
    args: argparse.Namespace, scenario: Scenario, log: JointLog, *, lag, shift: float
) -> EstimatorSettings:
    """The scenario's estimator settings with the --model's torque time law and the log's hold period."""
    settings = EstimatorSettings.from_scenario(scenario)
    if np.any(lag) and (np.any(settings.torque_lag_s) or settings.torque_delay_s):
        key = "torque_lag_s" if np.any(settings.torque_lag_s) else "torque_delay_s"
        raise BadInput(
            f"{args.scenario}: estimator.{key}: the --model's torque lag is undone on the logged "
            "signal (its noise after the filter); not with another time law"
        )
    if shift:
        if settings.torque_delay_s:
            raise BadInput(f"{args.scenario}: estimator.torque_delay_s: also set by the --model's pure delay")
        settings = dataclasses.replace(settings, torque_delay_s=shift)
    if settings.torque_signal == "held" and not scenario.estimator.hold_period_s:
        # A log's torque is held for the log's own sample period; the scenario's plant step only
        # describes the simulator's logs (a 100 Hz robot log would otherwise be all gaps).
        settings = dataclasses.replace(settings, hold_period_s=float(np.median(np.diff(log.t))))
    return settings


def _estimate_doc(
    args: argparse.Namespace,
    scenario: Scenario,
    log: JointLog,
    est,
    *,
    history: list[dict],
    settings,
    prior,
    prior_nominal,
    truth,
    corrections,
) -> dict:
    """estimate.json: the final estimate, its inputs and the update history."""
    final = est.estimate
    doc = final.to_json()
    doc.update(
        {
            "log": str(Path(args.log).resolve()),
            "scenario": scenario.source,
            "samples": int(len(log)),
            "estimate": {"nominal": doc["nominal"], "lower": doc["lower"], "upper": doc["upper"]},
            "prior": {
                "nominal": prior_nominal.tolist(),
                "lower": None if prior is None else prior[0].tolist(),
                "upper": None if prior is None else prior[1].tolist(),
            },
            "model": corrections,
            "truth": None if truth is None else {"theta": truth.tolist(), "dumbbell": scenario.payload.dumbbell},
            "contains_truth": None if truth is None else final.contains(truth),
            "mass_error_rel": None if truth is None else float((final.theta_e[0] - truth[0]) / truth[0]),
            "settings": _settings_record(settings),
            "update_period_s": scenario.planner.replan_period_s,
            "sysid": {"updates": len(history), "update_time_s": [h["update_time_s"] for h in history]},
            "history": history,
            "messages": est.messages,
        }
    )
    return doc


def _print_corrections(corrections: dict | None) -> None:
    """The --model's corrections: what was applied, what the estimator's model has no term for."""
    if corrections:
        print(
            f"model: {corrections['starting_model']} corrected by {', '.join(corrections['applied']) or 'nothing'}"
            + (
                f"; not applied (no term in the estimator's model): {', '.join(corrections['not_applied'])}"
                if corrections["not_applied"]
                else ""
            )
        )


def cmd_sysid(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario, overrides=args.scenario_text)
    lag, shift, corrections = 0.0, 0.0, None
    if args.model:
        robot, lag, shift, corrections = corrected_model(args.model)
    else:
        robot = robot_from_scenario(scenario)
    log = read_log(args.log, robot.n, args.topic, joints=args.joints or list(robot.joint_params.names))
    settings = _sysid_settings(args, scenario, log, lag=lag, shift=shift)
    ii = scenario.initial_interval
    prior = (np.array(ii.lower, float), np.array(ii.upper, float))
    prior_nominal = np.array(ii.nominal, float)
    if args.model and not args.scenario:  # the default scenario's prior is about its own robot and payload
        prior, prior_nominal = None, robot.theta_e
    # Only a scenario the user gives says what the log holds; the default one's dumbbell does not.
    truth = payload_truth(scenario, robot) if args.scenario else None
    try:
        est, history = run_sysid(
            log,
            robot,
            settings,
            period_s=scenario.planner.replan_period_s,
            prior=prior,
            prior_nominal=prior_nominal,
            torque_lag_s=lag,
        )
    except EstimatorError as err:
        raise BadInput(f"{args.log}: {err}") from err
    if not history:
        span = float(log.t[-1] - log.t[0])
        raise BadInput(
            f"{args.log}: too little data: {len(log)} samples over {span:.3g} s do not make two gap-free "
            f"segments of estimator.horizon_s = {settings.horizon_s} s (gaps > {settings.max_gap_s} s split them)"
        )
    final = est.estimate
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    doc = _estimate_doc(
        args,
        scenario,
        log,
        est,
        history=history,
        settings=settings,
        prior=prior,
        prior_nominal=prior_nominal,
        truth=truth,
        corrections=corrections,
    )
    (out / "estimate.json").write_text(json.dumps(doc, indent=2, default=float))
    title = f"{Path(args.log).name}: {len(history)} updates, cond(Y) = {final.cond_Y:.3g}, case {final.case}"
    plot_intervals(out / "intervals.png", final, prior_nominal, truth=truth, title=title)
    plot_history(out / "history.png", history, truth)
    verdict = "truth: unknown (no payload given)" if truth is None else f"truth inside: {final.contains(truth)}"
    _print_corrections(corrections)
    print(
        f"m = {final.theta_e[0]:.4g} kg in [{final.lower[0]:.4g}, {final.upper[0]:.4g}], "
        f"{'consistent' if final.consistent else 'INCONSISTENT with the declared bounds'}; {verdict}; "
        f"wrote {out / 'estimate.json'}"
    )
    if final.quadrature_assumption == "unverified":  # a log holds only the samples: A5 cannot be checked
        print(
            "rests on A5 unverified: the motion between the log's samples is assumed resolved by them "
            "(docs/guarantees.md A5; estimate.json quadrature_assumption)"
        )
    # Exit 1 when identification failed: the data contradict the declared bounds or the truth is outside.
    return 0 if final.consistent and doc["contains_truth"] is not False else 1
