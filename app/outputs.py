"""The files of a run (app/online.py run_online): summary.json, log.csv (the joint log with the
desired trajectory, the command and the estimate in force), the plots and replay.html."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pydrake.geometry import Meshcat
    from pydrake.systems.framework import Context
    from safesysid.online_diagram import OnlineDiagram
    from safesysid.summary import Identified, RunLogs
    from safesysid.systems.config import Scenario
    from safesysid.systems.model.robot_model import RobotModel
    from safesysid.systems.planner.safe_planner import PlanResult

ESTIMATE_COLUMNS = (("nominal", ""), ("lower", "_lo"), ("upper", "_hi"))


def prior_rows(built: OnlineDiagram) -> list[np.ndarray]:
    """[nominal, lower, upper] of the end effector's prior (the controller's before any update)."""
    robot = built.arm.robot
    theta0, box = built.theta_prior
    return [theta0[robot.ee_slice], box.lo[robot.ee_slice], box.hi[robot.ee_slice]]


def estimate_in_force(built: OnlineDiagram, t: np.ndarray, history: list[dict]) -> list[np.ndarray]:
    """[nominal, lower, upper] of the end-effector estimate in force at each sample (rows of t):
    the prior until the first update."""
    first = prior_rows(built)
    times = np.array([h["t"] for h in history])
    idx = np.searchsorted(times, t, side="right") - 1
    return [np.array([first[j]] + [h[key] for h in history])[idx + 1] for j, (key, _) in enumerate(ESTIMATE_COLUMNS)]


def write_log(out: Path, built: OnlineDiagram, logs: RunLogs, *, history: list[dict]) -> None:
    """log.csv: the joint log, the desired q, v, a, the command and the estimate in force."""
    from safesysid.joint_log import write_joint_log
    from safesysid.systems.model.inertial import NAMES
    from safesysid.systems.model.joint_data import JointLog

    n, desired = built.arm.robot.n, logs.desired
    extra = {f"qd{k + 1}": desired[:, k] for k in range(n)}
    extra.update({f"vd{k + 1}": desired[:, n + k] for k in range(n)})
    extra.update({f"ad{k + 1}": desired[:, 2 * n + k] for k in range(n)})
    extra.update({f"u{k + 1}": logs.command[:, k] for k in range(n)})
    for values, (_, suffix) in zip(estimate_in_force(built, logs.t, history), ESTIMATE_COLUMNS):
        for k, pname in enumerate(NAMES):
            extra[f"est_{pname}{suffix}"] = values[:, k]
    write_joint_log(out / "log.csv", JointLog(logs.t, logs.q, logs.v, logs.measured_torque), extra)


def write_plots(
    out: Path, built: OnlineDiagram, logs: RunLogs, *, summary: dict, ident: Identified, context: Context, title: str
) -> None:
    """tracking, clearance, joints, conditioning, intervals and (after an update) mass plots."""
    from safesysid import figures, report

    arm, robot, history = built.arm, built.arm.robot, ident.history
    limit = robot.joint_params.torque_limit
    report.plot_tracking(
        out / "tracking.png",
        logs.t,
        logs.error,
        bound=built.tracking.position,
        torque_ratio=np.max(np.abs(logs.command) / limit, 1),
    )
    rec = built.monitor.record(built.monitor.GetMyContextFromRoot(context))
    report.plot_clearance(
        out / "clearance.png", np.array(rec.times), np.array(rec.clearance), phases=figures.phases_of(summary)
    )
    figures.write_run_figures(out, summary, history, torque_limit=limit)  # joints, conditioning
    # The identified body is the last link + gripper + payload: say so, and show the prior behind the intervals.
    truth = np.asarray(summary["payload_true"]["theta"])
    body = report.identified_body_text(
        truth[0], *((arm.dumbbell.name, arm.dumbbell.mass_kg) if arm.dumbbell else ("", None))
    )
    first = prior_rows(built)
    prior = (first[1], first[2])
    est = ident.estimate
    nominal, lo, hi = (np.asarray(x) for x in (est.nominal, est.lower, est.upper))
    report.plot_intervals(
        out / "intervals.png", nominal, lo, upper=hi, truth=truth, title=f"{title}; {body}", prior=prior
    )
    if history:
        report.plot_estimate_history(
            out / "mass.png",
            [0.0] + [h["t"] for h in history],
            [first[0]] + [h["nominal"] for h in history],
            lower=[first[1]] + [h["lower"] for h in history],
            upper=[first[2]] + [h["upper"] for h in history],
            truth=truth,
            prior=prior,
            title=body,
        )


def write_replay(
    out: Path, built: OnlineDiagram, logs: RunLogs, *, summary: dict, scenario: Scenario, context: Context
) -> None:
    """replay.html (with a Meshcat visualizer) and its phase banner."""
    from safesysid import figures, viz

    arm, robot, meshcat = built.arm, built.arm.robot, built.meshcat
    # After the release the welded payload is empty (no mass, no collision) but still drawn: hide it.
    released = [e["t"] for e in summary["events"] if e["kind"] == "release"]
    hidden = [(viz.body_path(arm.payload_frame_name()), released[0])] if released else []
    n = robot.n
    phases = figures.phases_of(summary)
    replay = viz.ReplayScene(robot, logs.t, logs.q, logs.desired[:, :n], phases, scenario.obstacles, hidden)
    viz.decorate(meshcat, built.visualizer, replay)
    if built.visualizer is not None:
        if built.planner is not None:
            planner_context = built.planner.GetMyContextFromRoot(context)
            draw_plans(meshcat, robot, built.planner.results(planner_context))
        viz.save_replay(meshcat, built.visualizer, out / "replay.html")
    viz.add_phase_banner(out / "replay.html", replay.phases)


def write_outputs(
    out: Path,
    built: OnlineDiagram,
    logs: RunLogs,
    *,
    summary: dict,
    ident: Identified,
    scenario: Scenario,
    context: Context,
) -> None:
    """Every file of a run in `out` (which exists)."""
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    write_log(out, built, logs, history=ident.history)
    title = f"{scenario.name} / {summary['method']}"
    write_plots(out, built, logs, summary=summary, ident=ident, context=context, title=title)
    write_replay(out, built, logs, summary=summary, scenario=scenario, context=context)


def draw_plans(meshcat: Meshcat, robot: RobotModel, results: Iterable[PlanResult]) -> None:
    """Each accepted plan's gripper-centre path, and its certified swept spheres (toggle)."""
    from safesysid import viz

    grasp = robot.extra["grasp_point"]
    for index, res in enumerate(r for r in results if r.ok):
        q, _, _ = res.evaluate(np.linspace(0.0, res.trajectory.duration, 150))
        kin = robot.forward_kinematics(q)
        ee = robot.end_effector
        viz.draw_plan(meshcat, kin.p[:, ee] + kin.R[:, ee] @ grasp, index)
        if "sphere_centres" in res.details:
            viz.draw_swept_spheres(meshcat, res.details["sphere_centres"], res.details["sphere_radii"], index=index)
