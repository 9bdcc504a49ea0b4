"""summary.json of a run (app/online.py run_online): the typed `Summary` that is its schema
(docs/schemas/summary.schema.json lists the same fields: tests/test_online.py), and `summarize`,
which reads it off a simulated online diagram: the referee's record, the loggers, the estimator's
history before the task phase, the planner's records and every system's events."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from safesysid.systems import methods
from safesysid.systems.estimation.system import ESTIMATE_EXTRA

if TYPE_CHECKING:
    from pydrake.systems.framework import Context
    from pydrake.systems.primitives import VectorLogSink
    from safesysid.online_diagram import OnlineDiagram
    from safesysid.systems.config import Scenario
    from safesysid.task_run import GuardedSimulator


class Omitted:
    """The value of a field summary.json leaves out (not null: the key is absent)."""

    def __repr__(self) -> str:
        return "OMITTED"


OMITTED = Omitted()


def omitted() -> dataclasses.Field:
    """A field's default when summary.json writes the key only in some runs."""
    return field(default=OMITTED, metadata={"optional": True})


def as_json(obj: object) -> object:
    """A summary dataclass as the dict summary.json holds, in field order, omitted keys left out."""
    if dataclasses.is_dataclass(obj):
        values = ((f.name, getattr(obj, f.name)) for f in dataclasses.fields(obj))
        return {name: as_json(value) for name, value in values if value is not OMITTED}
    return obj


@dataclass(kw_only=True)
class PayloadTruth:
    theta: list[float]  # the identified body's truth: last link + gripper + dumbbell
    dumbbell: str | None


@dataclass(kw_only=True)
class EstimateSummary:
    """The identification phase's estimate of the identified body (or the prior, or the adaptive law's)."""

    nominal: list[float]
    lower: list[float]
    upper: list[float]
    consistent: bool
    # the estimator's last update's data-driven box before pruning and the paper's first-order interval
    data_lower: list[float] | None | Omitted = omitted()
    data_upper: list[float] | None | Omitted = omitted()
    first_order_lower: list[float] | None | Omitted = omitted()
    first_order_upper: list[float] | None | Omitted = omitted()
    # A5 at the last update: unverified | checked | certified | violated (docs/guarantees.md A5)
    quadrature_assumption: str | Omitted = omitted()
    source: str  # estimator (Algorithm 1) | adaptation | none (the prior)


@dataclass(kw_only=True)
class PlannerSummary:
    iterations: int
    solve_time_s: list[float]
    deadline_s: float
    missed_deadlines: int
    brakes: int
    solver: str
    budget: str  # iterations (deterministic) | wall_time (real time)
    status: list[str]
    cond_W: list[float | None]
    refined: list[bool]  # planner.point_refinement: certified on its own k


@dataclass(kw_only=True)
class SysidSummary:
    updates: int
    update_time_s: list[float]


@dataclass(kw_only=True)
class Summary:
    """One run's verdict, safety margins and estimate: summary.json, field for field."""

    scenario: str
    method: str
    seed: int
    success: bool
    failure: str | None
    phase: str | None
    failure_time_s: float | None
    collisions: int
    min_clearance_m: float
    max_torque_ratio: float
    max_commanded_torque_ratio: float
    max_joint_limit_ratio: float
    max_velocity_ratio: float
    max_tracking_error_rad: float
    tracking_bound_rad: float
    max_tracking_error_ratio: float
    tracking_bound_per_joint_rad: list[float]
    placement_error_m: float | None
    task: dict | None
    payload_true: PayloadTruth
    robot_parameters: str  # the simulated arm's: nominal | drawn | corner (A1)
    estimate: EstimateSummary
    events: list[dict]
    contains_truth: bool
    cond_Y: float
    planner: PlannerSummary
    sysid: SysidSummary
    robust_input: dict | None
    wall_time_s: float
    sim_time_s: float
    # written by `safesysid run` when Ctrl-C stopped the run (app/run_cli.py)
    interrupted: bool | Omitted = omitted()
    interrupted_at_s: float | Omitted = omitted()

    def to_json(self) -> dict:
        return as_json(self)


@dataclass
class RunLogs:
    """The loggers' samples of a run, one row per plant step."""

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    measured_torque: np.ndarray
    command: np.ndarray
    desired: np.ndarray  # [q_d, v_d, a_d]
    error: np.ndarray  # q_d - q, continuous joints wrapped to (-pi, pi]


@dataclass
class SimulatedRun:
    """A built online diagram after its simulation (app/online.py simulate)."""

    sim: GuardedSimulator
    context: Context
    switch_time_s: float  # inf: no task phase
    end_time_s: float
    task: dict | None  # run_task_phase's summary, None without a task phase


def log_of(sink: VectorLogSink, context: Context) -> tuple[np.ndarray, np.ndarray]:
    data = sink.FindLog(context)
    return data.sample_times().copy(), data.data().T.copy()


def read_logs(built: OnlineDiagram, context: Context) -> RunLogs:
    t, state = log_of(built.loggers["state"], context)
    _, measured = log_of(built.loggers["measured_torque"], context)
    _, command = log_of(built.loggers["command"], context)
    _, desired = log_of(built.loggers["desired"], context)
    robot = built.arm.robot
    n = robot.n
    q, v = state[:, :n], state[:, n:]
    error = desired[:, :n] - q
    cont = robot.joint_params.continuous
    error[:, cont] = np.angle(np.exp(1j * error[:, cont]))
    return RunLogs(t, q, v, measured, command, desired, error)


def merge_events(*sources: Iterable[dict]) -> list[dict]:
    """One list of {t, kind, detail} from several systems' event lists, in time order (stable:
    events at the same instant keep their order within a source)."""
    return sorted((dict(e) for source in sources for e in source), key=lambda e: e["t"])


def robust_input_summary(diag: np.ndarray, armour_active: np.ndarray, identification: np.ndarray) -> dict:
    """How hard ARMOUR's robust input worked, per phase, from its diagnostics log (rows [V_bar, h,
    lambda, |r|, |w_bar|], one per logged step): the fraction of steps with lambda > 0 (the
    robust input v = lambda r/|r| acting), the largest lambda [N m], the smallest barrier
    h = V_max - V_bar [J] and the largest |w_bar| [N m] (the model uncertainty it must cover)."""
    out = {}
    for name, mask in (("identification", armour_active & identification), ("task", armour_active & ~identification)):
        rows = diag[mask]  # the loggers share the period: one row per logged step
        if len(rows):
            out[name] = {
                "active_fraction": float(np.mean(rows[:, 2] > 0)),
                "max_lambda_Nm": float(rows[:, 2].max()),
                "min_h_J": float(rows[:, 1].min()),
                "max_w_bar_Nm": float(rows[:, 4].max()),
            }
    return out


@dataclass
class Identified:
    """What the identification phase left: its estimate and the estimator's history before the switch."""

    estimate: EstimateSummary
    history: list[dict]
    cond_y: float
    events: list[dict]


def identified(built: OnlineDiagram, run: SimulatedRun, spec: methods.MethodSpec) -> Identified:
    """The estimator's last update before the task phase (the estimator keeps sampling in the
    task phase, the payload's release included: nothing after the switch is the identification's);
    without an estimator the prior, or the adaptive law's last estimate holding the payload."""
    est, ctx, robot = built.estimator, run.context, built.arm.robot
    if est is None:
        theta0, box = built.theta_prior
        theta_e0, lo, hi = theta0[robot.ee_slice], box.lo[robot.ee_slice], box.hi[robot.ee_slice]
        if spec.identifies == methods.ADAPTATION:  # the adaptive law's estimate, inside its projection box
            # its last value holding the payload: after the release the law adapts to the bare gripper
            t_est, adapted = log_of(built.loggers["adaptive_estimate"], ctx)
            held = t_est < ((run.task or {}).get("release_time_s") or np.inf)
            theta_e0 = adapted[held][-1] if held.any() else adapted[0]
        return Identified(_estimate(theta_e0, lo, hi, True, {}, spec), [], float("nan"), [])
    est_ctx = est.GetMyContextFromRoot(ctx)
    history = [h for h in est.history(est_ctx) if h["t"] <= run.switch_time_s]
    if history:
        theta_e0, lo, hi = (np.asarray(history[-1][k], float) for k in ("nominal", "lower", "upper"))
    else:
        theta_e0, lo, hi = est.final_estimate(est_ctx)
    consistent = all(h["consistent"] for h in history)
    extra = {k: history[-1][k] for k in ESTIMATE_EXTRA} if history else {}
    events = [e for e in est.events(est_ctx) if e["t"] <= run.switch_time_s]
    cond_y = history[-1]["cond_Y"] if history else float("nan")
    return Identified(_estimate(theta_e0, lo, hi, consistent, extra, spec), history, cond_y, events)


def _estimate(theta_e0, lo, hi, consistent, extra: dict, spec: methods.MethodSpec) -> EstimateSummary:
    return EstimateSummary(
        nominal=np.asarray(theta_e0).tolist(),
        lower=np.asarray(lo).tolist(),
        upper=np.asarray(hi).tolist(),
        consistent=bool(consistent),
        **extra,
        source=spec.identifies,
    )


def planner_summary(plans: list[dict], events: list[dict], scenario: Scenario, *, method: str) -> PlannerSummary:
    solve_times = [p["solve_time_s"] for p in plans]
    deadline = scenario.planner.replan_period_s
    return PlannerSummary(
        iterations=len(plans),
        solve_time_s=solve_times,
        deadline_s=deadline,
        missed_deadlines=int(sum(t_ > deadline for t_ in solve_times)),
        brakes=sum(e["kind"] == "brake" for e in events),
        solver=scenario.planner.solver if method != "random" else "random",
        budget=scenario.planner.budget,
        status=[p["status"] for p in plans],
        cond_W=[p.get("cond") for p in plans],
        refined=[p.get("refined", False) for p in plans],
    )


# The SafetyMonitor's record.summary() keys summary.json copies.
SAFETY_KEYS = (
    "collisions",
    "min_clearance_m",
    "max_torque_ratio",
    "max_commanded_torque_ratio",
    "max_joint_limit_ratio",
    "max_velocity_ratio",
)


def summarize(
    built: OnlineDiagram, run: SimulatedRun, logs: RunLogs, *, scenario: Scenario, method: str, seed: int, wall_s: float
) -> tuple[Summary, Identified]:
    """The run's Summary, and the identification phase's estimate and history (for the figures)."""
    from safesysid.systems.plant.faults import scenario_events
    from safesysid.task_run import judge

    ctx, arm, spec = run.context, built.arm, methods.method_spec(method)
    record = built.monitor.record(built.monitor.GetMyContextFromRoot(ctx))
    safety = record.summary()
    truth = arm.true_theta()[arm.robot.ee_slice]
    ident = identified(built, run, spec)
    plans, planner_events = [], []
    if built.planner is not None:
        planner_context = built.planner.GetMyContextFromRoot(ctx)
        plans, planner_events = built.planner.records(planner_context), built.planner.events(planner_context)
    task = run.task
    task_events = task.pop("events") if task else []
    failure = [run.sim.failure] if run.sim.failure else []
    events = merge_events(  # every system's, in time order
        ident.events, planner_events, task_events, arm.fault_events(ctx), scenario_events(scenario), failure
    )
    bound = np.asarray(built.tracking.position, float)
    ratio_t = np.max(np.abs(logs.error) / bound, axis=1)  # per joint: Kr differs between joints
    # The tube is ARMOUR's certificate: a PID or adaptive phase claims none, so is not judged on it.
    in_identification = np.asarray(logs.t) < run.switch_time_s
    armour_active = np.where(in_identification, spec.first_controller == "armour", spec.controller == "armour")
    tracking_ratio = np.where(armour_active, ratio_t, 0.0)
    failed_at = run.sim.failure["t"] if run.sim.failure else None
    failure, phase, t_fail = judge(
        record,
        plans,
        logs.t,
        tracking_ratio=tracking_ratio,
        task=task,
        t_switch=run.switch_time_s,
        simulation_failed_at=failed_at,
    )
    robust = None
    if "armour" in built.loggers:
        _, diag = log_of(built.loggers["armour"], ctx)
        robust = robust_input_summary(diag, armour_active, in_identification)
    est = ident.estimate
    summary = Summary(
        scenario=scenario.name,
        method=method,
        seed=seed,
        success=failure is None,
        failure=failure,
        phase=phase,
        failure_time_s=t_fail,
        **{key: safety[key] for key in SAFETY_KEYS},
        max_tracking_error_rad=float(np.abs(logs.error).max()),
        tracking_bound_rad=float(np.max(bound)),
        max_tracking_error_ratio=float(ratio_t.max()),
        tracking_bound_per_joint_rad=bound.tolist(),
        placement_error_m=task["placement"]["error_m"] if task else None,
        task=task,
        payload_true=PayloadTruth(theta=truth.tolist(), dumbbell=arm.dumbbell.name if arm.dumbbell else None),
        robot_parameters=scenario.plant.robot_parameters,
        estimate=est,
        events=events,
        contains_truth=bool(np.all((np.asarray(est.lower) <= truth) & (truth <= np.asarray(est.upper)))),
        cond_Y=ident.cond_y,
        planner=planner_summary(plans, events, scenario, method=method),
        sysid=SysidSummary(updates=len(ident.history), update_time_s=[h["update_time_s"] for h in ident.history]),
        robust_input=robust,
        wall_time_s=wall_s,
        sim_time_s=float(run.end_time_s),
    )
    return summary, ident
