"""The task phase of a run (app/online.py): the TaskPhaseSource of a scenario, the driver that
advances a built run through the task, the release and the settling, and the judgement of a run
(its first failure and the phase it happened in). The math is in systems/task/phase.py."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import Context
    from safesysid.online_diagram import OnlineDiagram
    from safesysid.systems.config import Scenario, Task
    from safesysid.systems.hardware.background import BackgroundWorker
    from safesysid.systems.model.payload import Dumbbell
    from safesysid.systems.model.robot_model import RobotModel
    from safesysid.systems.planner.trajectory_source import PhaseState, TaskPhaseSource
    from safesysid.systems.plant.safety_monitor import SafetyRecord
    from safesysid.systems.task.problem import TaskProblem
    from safesysid.systems.task.trajectory import TaskResult


def released_parameters(
    robot: RobotModel, scenario: Scenario, method: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta0, lower, upper) after the release: the bare end effector (the model's own) with
    the rest of the robot as in the method's prior box."""
    from safesysid.systems import methods
    from safesysid.systems.model.uncertainty import parameter_box

    if methods.method_spec(method).theta0_source == methods.NO_PAYLOAD:  # exact: bare, no uncertainty
        theta0 = robot.theta.copy()
        return theta0, theta0, theta0
    ee = robot.theta[robot.ee_slice]
    ratio = scenario.noise.theta_r_ratio
    floors = scenario.noise.theta_r_floor
    theta0, box = parameter_box(robot, ee, ee, ee, rest_ratio=ratio, friction_ratio=ratio, floors=floors)
    return theta0, box.lo, box.hi


def make_task_source(
    robot: RobotModel,
    scenario: Scenario,
    switch_time_s: float,
    *,
    problem: TaskProblem,
    plan: TaskResult,
    held: Dumbbell | None = None,
    certify: bool = False,
    worker: BackgroundWorker | None = None,
) -> TaskPhaseSource:
    """The TaskPhaseSource of a scenario whose task trajectory `plan` (TaskResult) solves `problem`;
    held: the payload in the gripper (the return move's geometry, systems/task_phase.return_move).
    certify: the task controller is ARMOUR, whose certificate the phase must carry (certify_task).
    worker: a wall-clock run's; the task is made there while the loop holds the arm
    (systems/hardware/task_source.py)."""
    from safesysid.systems.planner.trajectory_source import TaskPhaseSource
    from safesysid.systems.task.phase import return_move

    def make_task(q_now, thetas):
        if not plan.ok:
            return [], [dict(kind="task_infeasible", detail=f"task trajectory {plan.status}: {plan.reason}")], {}
        back = return_move(problem, q_now, scenario.task.return_duration_s, held=held)
        curves, events = [], []
        if back is not None:
            solve = f"{back.status} ({back.solver}, {back.solve_time_s:.2f} s)"
            events.append(dict(kind="return_move", detail=f"to q0 in {scenario.task.return_duration_s:.2f} s: {solve}"))
            if not back.ok:
                return [], events + [dict(kind="task_infeasible", detail=f"no return move: {back.reason}")], {}
            curves.append(back.trajectory)
        curves.append(plan.trajectory)
        report, certified = {"time_scale": 1.0}, ""  # another controller than ARMOUR claims no certificate
        if certify:
            curves, report, certified = certify_task(problem, curves, thetas, task=scenario.task)
            if not curves:
                return [], events + [dict(kind="task_uncertified", detail=certified)], report
        cache = plan.details.get("cache", "")
        detail = f"task trajectory {curves[-1].duration:.2f} s ({plan.status}, cache {cache}){certified}"
        events.append(dict(kind="task_start", detail=detail))
        return curves, events, report

    args = (robot.n, 14 * robot.n, scenario.q0_rad)
    if worker is not None:
        from safesysid.systems.hardware.task_source import WallClockTaskSource

        return WallClockTaskSource(*args, switch_time_s=switch_time_s, make_task=make_task, worker=worker)
    return TaskPhaseSource(*args, switch_time_s=switch_time_s, make_task=make_task)


def certify_task(problem: TaskProblem, curves: list, thetas: tuple, *, task: Task) -> tuple[list, dict, str]:
    """ARMOUR's certificate of the task phase's curves (the return move, the task trajectory)
    with the box latched at the switch (task_check.phase_certificate: sup |u| / limit over the
    tube and the box): the curves played at the smallest scale of the grid 1 .. task.max_time_scale
    (step task.time_scale_step) whose certificate is <= 1, or [] (refused: task_uncertified, the
    arm holds). Returns (curves, report for summary.json's task, text for the event)."""
    from safesysid.systems.task.check import phase_certificate, smallest_certified_scale, time_scale_grid, time_scaled

    scales = time_scale_grid(task.max_time_scale, task.time_scale_step)
    found = smallest_certified_scale(lambda scale: phase_certificate(problem, curves, thetas, scale=scale), scales)
    unscaled = found.tried[0][1]
    report = {
        "time_scale": found.time_scale,
        "uncertified": not found.certified,
        "certified_torque_ratio": found.ratio,
        "certified_torque_ratio_unscaled": unscaled,
        "time_scales_tried": [list(x) for x in found.tried],
    }
    if not found.certified:
        text = (
            f"torque certificate {unscaled:.3f} at 1x and {found.ratio:.3f} at {scales[-1]:g}x "
            "(task.max_time_scale) exceeds the limit: the task is refused, the arm holds"
        )
        return [], report, text
    text = f", {found.time_scale:g}x slower" if found.time_scale > 1 else ""
    text += f", torque certificate {found.ratio:.3f}" + (f" (1x: {unscaled:.3f})" if found.time_scale > 1 else "")
    return [time_scaled(c, found.time_scale) for c in curves], report, text


def judge(
    record: SafetyRecord,
    plans: list[dict],
    t: np.ndarray,
    *,
    tracking_ratio: np.ndarray,
    task: dict | None,
    t_switch: float,
    simulation_failed_at: float | None = None,
) -> tuple[str | None, str | None, float | None]:
    """(failure, phase, time) of the first failure of a run in contracts.md's order, or
    (None, None, None). Torque is judged on the controller's command before saturation (the
    saturated torque can never exceed the limit). record: the SafetyMonitor's; tracking_ratio:
    max over joints of |error| / tube bound at the logger's times t; task: _run_task_phase's
    summary (None: no task phase); simulation_failed_at: when the plant's solver failed (GuardedSimulator)."""
    from safesysid.systems.task.phase import first_failure

    times = np.asarray(record.times, float)

    def above(values, limit):
        return times[np.asarray(values, float) > limit]

    infeasible = [p["t_s"] for p in plans[:1] if not p["ok"]]
    placement, refused = [], []
    if task is not None:
        refused = [task["switch_time_s"]] if task.get("uncertified") else []
        infeasible += [] if task["executed"] or refused else [task["switch_time_s"]]
        place = task["placement"]
        if place["error_m"] is not None and not place["error_m"] <= place["tolerance_m"]:
            placement = [task["release_time_s"]]
    checks = [
        ("collision", times[np.asarray(record.clearance, float) < 0]),
        ("torque_limit", above(record.commanded_ratio, 1.0 + 1e-9)),
        ("joint_limit", above(record.joint_ratio, 1.0)),
        ("velocity_limit", above(record.velocity_ratio, 1.0)),
        ("planner_infeasible", infeasible),
        ("task_uncertified", refused),
        ("tracking", np.asarray(t)[tracking_ratio > 1 + 1e-9]),
        ("simulation", [] if simulation_failed_at is None else [simulation_failed_at]),
        ("placement", placement),
    ]
    return first_failure(checks, t_switch)


def task_certificate_summary(st: PhaseState, truth: np.ndarray | None, robot: RobotModel) -> dict:
    """summary.json task fields of the certificate (certify_task's report, PhaseState st): the
    scale played and the task trajectory's duration (None when refused or not found), and whether
    the latched box holds the true payload (else its certificate certifies nothing real: wrong;
    None when the truth is not known here: an arm over LCM)."""
    keys = ("time_scale", "certified_torque_ratio", "certified_torque_ratio_unscaled")
    report = {**dict.fromkeys(keys), "uncertified": False, "time_scales_tried": [], **st.report}
    contains = None
    if truth is not None and st.thetas:
        lo, hi = (np.asarray(x, float)[robot.ee_slice] for x in st.thetas[1:])
        ee = np.asarray(truth, float)[robot.ee_slice]
        contains = bool(np.all((lo <= ee) & (ee <= hi)))
    return {
        **report,
        "duration_s": float(st.curves[-1].curve.duration) if st.ready else None,
        "certificate_box_contains_payload": contains,
    }


class GuardedSimulator:
    """A Simulator whose AdvanceTo turns a failure of the plant's solver (the state diverged, e.g.
    a controller exciting an elastic joint) into a judged failure: the run stops there, its
    summary is written with failure "simulation" and the event, instead of a traceback."""

    def __init__(self, simulator: Simulator) -> None:
        self.simulator = simulator
        self.failure: dict | None = None  # the event {t, kind, detail}

    def __getattr__(self, name):
        return getattr(self.simulator, name)

    def AdvanceTo(self, t: float) -> None:  # noqa: N802 (Drake's name)
        if self.failure is not None:
            return
        try:
            self.simulator.AdvanceTo(t)
        except RuntimeError as err:
            now = self.simulator.get_context().get_time()
            detail = f"the plant's solver failed ({err}): the simulated state diverged; the run stops here"
            self.failure = dict(t=now, kind="simulation_failed", detail=detail)


def run_task_phase(built: OnlineDiagram, sim: Simulator, scenario: Scenario, *, method: str) -> dict:
    """Advance a built run through identification, the task phase, the release and the settling;
    returns the task's summary (placement measured on the simulated payload pose)."""
    from safesysid.systems.task.phase import placement_target

    ctx = sim.get_mutable_context()
    arm, source = built.arm, built.source
    # The switch fires at switch_time_s; one step later its curves are in the context.
    sim.AdvanceTo(source.switch_time_s + scenario.plant.time_step_s)
    st = source.phase_state(source.GetMyContextFromRoot(ctx))
    certificate = task_certificate_summary(st, arm.true_theta(), arm.robot)
    t_release = max(st.t_end, ctx.get_time())
    sim.AdvanceTo(t_release)
    release_xyz = None
    if arm.released_body is not None and st.ready:
        release_xyz = arm.release(ctx).translation()
        switch_to_released(built, ctx, scenario, method=method, t=t_release, where=release_xyz)
    end = t_release + scenario.task.settle_time_s
    sim.AdvanceTo(end)
    target, kind = placement_target(scenario, arm.dumbbell)
    settled = arm.payload_pose(ctx).translation() if arm.dumbbell is not None else None
    measured = release_xyz if kind == "release" and release_xyz is not None else settled
    error = None if target is None else float(np.linalg.norm(measured - target))
    placement = {
        "kind": kind or None,
        "target_m": _as_list(target),
        "measured_m": _as_list(measured),
        "release_m": _as_list(release_xyz),
        "error_m": error,
        "tolerance_m": scenario.task.placement_tolerance_m,
        "speed_at_end_m_s": arm.payload_speed(ctx) if arm.dumbbell is not None else None,
    }
    return task_summary(
        built, ctx, scenario, st=st, certificate=certificate, times=(t_release, end), placement=placement
    )


def _as_list(x) -> list | None:
    return None if x is None else np.asarray(x, float).tolist()


def switch_to_released(
    built: OnlineDiagram, ctx: Context, scenario: Scenario, *, method: str, t: float, where: np.ndarray | None
) -> None:
    """The payload has left the gripper at t: the controller gets the bare end effector's
    parameters (released_parameters), logged as the release event."""
    source = built.source
    at = "" if where is None else f" at {np.round(where, 4).tolist()} m"
    event = dict(t=t, kind="release", detail=f"payload released{at}; controller: bare end effector")
    source.set_thetas(
        source.GetMyMutableContextFromRoot(ctx), released_parameters(built.arm.robot, scenario, method), event
    )


def task_summary(
    built: OnlineDiagram,
    ctx: Context,
    scenario: Scenario,
    *,
    st: PhaseState,
    certificate: dict,
    times: tuple[float, float],
    placement: dict,
) -> dict:
    """summary.json's task section: times (release, end), the trajectory, its certificate, the placement."""
    _, plan = built.task
    source = built.source
    return {
        "switch_time_s": float(st.t_switch),
        "release_time_s": float(times[0]),
        "end_time_s": float(times[1]),
        "executed": bool(st.ready),
        "return_move": len(st.curves) > 1,
        "trajectory": {
            "status": plan.status,
            "solver": plan.solver,
            "cost": plan.cost,
            "cache": plan.details.get("cache"),
            "payload_model": scenario.task.payload_model,
        },
        **certificate,
        "placement": placement,
        "events": source.events(source.GetMyContextFromRoot(ctx)),
    }
