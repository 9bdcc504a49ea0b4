"""Algorithm 2 as one Drake diagram: real arm station <- controller (closed_loop.add_controller)
<- ExcitingPlanner, with the SysIdEstimator feeding (theta0, [theta]) back to the planner,
refereed by the SafetyMonitor.
The controller takes its (theta0, [theta]) from the planner: those the executing plan was
certified with (systems/planner/system.py), never the estimator's latest.

Methods: the paper's table of comparisons, as data in systems/methods.py (METHODS_SPEC): the
identification phase is the method's excitation (the planner's exciting or random plans, the
Fourier trajectory of grav-pid-excit, or none: the arm holds q0), tracked by its controller.

Task phase (scenario `task` section; systems/task/phase.py): a TaskPhaseSource sits between the
planner and the controller. One plant step after the identification horizon (at t = 0 for
methods that do not identify, which then have no planner) it latches the method's parameters
(ours: the identified box), frozen for the task, and plays the move back to q0 and the cached
task trajectory, slower or not at all when ARMOUR's certificate with that box needs it
(app/task_run.certify_task: task_uncertified, the arm holds); at its
end run_online releases the payload (RealArm.release), gives the controller the bare end
effector, lets the payload settle and measures the placement on the simulated pose. The
SafetyMonitor referees the whole run, both phases.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from safesysid.scenario import Scenario, robot_from_scenario, task_enabled
from safesysid.systems import config, methods
from safesysid.systems.estimation.system import ESTIMATE_EXTRA
from safesysid.systems.model import parameter_sources

if TYPE_CHECKING:
    from pydrake.geometry import Meshcat, MeshcatVisualizer
    from pydrake.systems.framework import Diagram
    from pydrake.systems.primitives import VectorLogSink
    from safesysid.systems.controller.armour import TrackingBounds
    from safesysid.systems.controller.systems import ControllerBase
    from safesysid.systems.estimation.system import SysIdEstimator
    from safesysid.systems.hardware.background import BackgroundWorker
    from safesysid.systems.math.intervals import Interval
    from safesysid.systems.model.payload import Dumbbell
    from safesysid.systems.model.robot_model import RobotModel
    from safesysid.systems.planner.safe_planner import PlanResult
    from safesysid.systems.planner.system import ExcitingPlanner
    from safesysid.systems.planner.trajectory_source import TaskPhaseSource
    from safesysid.systems.plant.arm_plant import RealArm
    from safesysid.systems.plant.safety_monitor import SafetyMonitor


def prior(robot: RobotModel, scenario: Scenario, method: str) -> tuple[np.ndarray, Interval]:
    """(theta0, [theta]) the controller and planner start from (parameter_sources.initial_parameters:
    Table II before an identification phase; "wrong", "grav-pid": the bare end effector, zero width)."""
    return parameter_sources.initial_parameters(methods.method_spec(method), robot, scenario)


@dataclass
class OnlineDiagram:
    diagram: Diagram
    arm: RealArm
    controller: ControllerBase
    planner: ExcitingPlanner | None  # None: no planner (Fourier excitation, or none)
    estimator: SysIdEstimator | None
    monitor: SafetyMonitor | None  # None: the arm is reached over LCM (its referee is the arm side's)
    loggers: dict[str, VectorLogSink]
    visualizer: MeshcatVisualizer | None
    meshcat: Meshcat | None
    theta_prior: tuple[np.ndarray, Interval]
    tracking: TrackingBounds
    source: TaskPhaseSource | None = None  # None: no task phase
    task: tuple = ()  # (TaskProblem, TaskResult) of the scenario's task


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


def _add_logger(builder, port, period, name):
    from pydrake.systems.primitives import LogVectorOutput

    sink = LogVectorOutput(port, builder, period)
    sink.set_name(f"log_{name}")
    return sink


def _add_planner(builder, robot, scenario, spec, tracking, arm, theta_prior, seed, estimator, worker=None):
    """Algorithm 2's planner as the method's excitation, fed by the estimator (or the prior when
    the method does not identify with it). Returns (planner, desired-trajectory port)."""
    from pydrake.systems.primitives import Multiplexer

    trajectory = spec.excitation.trajectory
    planner = builder.AddSystem(
        make_planner_system(robot, scenario, trajectory, tracking, arm.dumbbell, theta_prior, seed, worker=worker)
    )
    planner.set_name("planner")
    desired = builder.AddSystem(Multiplexer([robot.n] * 3))
    desired.set_name("desired_q_v_a")
    for k, name in enumerate(("q_desired", "v_desired", "a_desired")):
        builder.Connect(planner.GetOutputPort(name), desired.get_input_port(k))
    theta0, box = theta_prior
    for k, (name, value) in enumerate(zip(("theta0", "theta_lower", "theta_upper"), (theta0, box.lo, box.hi))):
        port = estimator.GetOutputPort(name) if estimator is not None else _constant(builder, value, f"prior_{k}")
        builder.Connect(port, planner.GetInputPort(name))
    if estimator is not None and estimator.HasOutputPort("consistent"):
        builder.Connect(estimator.GetOutputPort("consistent"), planner.GetInputPort("estimate_consistent"))
    else:
        builder.Connect(_constant(builder, [1.0], "estimate_consistent"), planner.GetInputPort("estimate_consistent"))
    return planner, desired.get_output_port()


def _excitation_without_planner(builder, spec, robot, scenario):
    """The desired-trajectory port of a method without a planner: the Fourier trajectory, or
    holding q0 (no identification phase)."""
    if spec.excitation is not None and spec.excitation.trajectory == methods.FOURIER:
        from safesysid.systems.excitation.fourier import fourier_excitation
        from safesysid.systems.excitation.source import FourierSource

        source = builder.AddSystem(FourierSource(fourier_excitation(robot, scenario).trajectory))
        source.set_name("fourier_excitation")
        return source.get_output_port()
    q0 = np.asarray(scenario.q0_rad, float)
    return _constant(builder, np.concatenate([q0, np.zeros(2 * robot.n)]), "hold_q0")


def _constant(builder, value, name):
    from pydrake.systems.primitives import ConstantVectorSource

    src = builder.AddSystem(ConstantVectorSource(np.asarray(value, float)))
    src.set_name(name)
    return src.get_output_port()


def make_planner_system(
    robot: RobotModel,
    scenario: Scenario,
    trajectory: str,
    tracking: TrackingBounds,
    dumbbell: Dumbbell | None,
    theta_prior: tuple[np.ndarray, Interval],
    seed: int,
    *,
    worker: BackgroundWorker | None = None,
) -> ExcitingPlanner:
    """trajectory: methods.EXCITING (scenario.planner.cost) or methods.RANDOM. With a worker:
    the wall-clock planner, whose calls run one period ahead in it (systems/hardware/background.py)."""
    from safesysid.systems.hardware.background import WallClockPlanner
    from safesysid.systems.model.torque_noise import DeclaredTorqueNoise
    from safesysid.systems.planner.safe_planner import SafePlanner
    from safesysid.systems.planner.system import ExcitingPlanner

    mode = "random" if trajectory == methods.RANDOM else scenario.planner.cost
    noise = DeclaredTorqueNoise.from_noise(scenario.noise)
    planner = SafePlanner(
        robot, scenario.planner, obstacles=scenario.obstacles, payload=dumbbell, tracking=tracking, declared_noise=noise
    )
    theta0, box = theta_prior
    f = scenario.faults
    system, extra = (ExcitingPlanner, {}) if worker is None else (WallClockPlanner, {"worker": worker})
    return system(
        planner,
        np.asarray(scenario.q0_rad, float),
        theta0,
        box.lo,
        box.hi,
        mode=mode,
        seed=seed,
        forced_failures={k: f.planner_failure_kind for k in f.planner_failure_calls},
        appearing=[(ob.t_s, ob) for ob in f.appearing_obstacles],
        **extra,
    )


def task_switch_time_s(scenario: Scenario, spec: methods.MethodSpec) -> float:
    """Start of the task phase: one plant step after the identification phase (so the
    estimator's update due at its end is in the latched box), or 0 without identification."""
    if spec.excitation is None:
        return 0.0
    return config.excitation_duration_s(spec, scenario) + scenario.plant.time_step_s


def make_estimator_system(
    robot: RobotModel,
    scenario: Scenario,
    update_period_s: float | None = None,
    stop_time_s: float = np.inf,
    *,
    worker: BackgroundWorker | None = None,
) -> SysIdEstimator:
    """The SysIdEstimator of a scenario: its estimator settings and initial interval, sampling at
    the plant step, updating every t_p (planner.replan_period_s unless given), until stop_time_s.
    With a worker: the wall-clock estimator, its updates run there (systems/hardware/background.py)."""
    from safesysid.systems.estimation import EstimatorSettings
    from safesysid.systems.estimation.system import SysIdEstimator
    from safesysid.systems.hardware.background import WallClockEstimator

    ii = scenario.initial_interval
    system, extra = (SysIdEstimator, {}) if worker is None else (WallClockEstimator, {"worker": worker})
    return system(
        robot,
        EstimatorSettings.from_scenario(scenario),
        scenario.plant.time_step_s,
        update_period_s or scenario.planner.replan_period_s,
        (np.array(ii.lower, float), np.array(ii.upper, float)),
        np.array(ii.nominal, float),
        stop_time_s=stop_time_s,
        **extra,
    )


def build_online(
    scenario: Scenario,
    method: str | None = None,
    meshcat: Meshcat | None = None,
    seed: int | None = None,
    *,
    worker: BackgroundWorker | None = None,
) -> OnlineDiagram:
    """worker: the wall-clock run's (app/online_lcm.py): planner and estimator calls run in it.
    scenario.arm.driver lcm: the arm is reached over LCM (systems/hardware/lcm_arm.py); the
    referee and the payload's release are the arm's, so no SafetyMonitor and no task phase here."""
    from pydrake.systems.framework import DiagramBuilder
    from safesysid.closed_loop import add_controller, add_phase_switch
    from safesysid.systems.controller.armour import tracking_bounds_for
    from safesysid.systems.plant.station import add_real_arm
    from safesysid.systems.task.phase import task_plan
    from safesysid.task_run import make_task_source

    method = method or scenario.method
    spec = methods.method_spec(method)
    robot = robot_from_scenario(scenario)
    h = scenario.plant.time_step_s
    over_lcm = scenario.arm.driver == "lcm"
    task = task_enabled(scenario) and not over_lcm
    builder = DiagramBuilder()
    if over_lcm:
        from safesysid.systems.hardware.lcm_arm import add_lcm_arm, make_lcm

        arm = add_lcm_arm(builder, scenario, robot, lcm=make_lcm(scenario))
    else:
        arm = add_real_arm(builder, scenario, robot=robot, seed=seed, releasable=task and not scenario.task.goal_q_rad)
    theta0, box = prior(robot, scenario, method)
    switches = task and spec.switches_controller  # grav-pid-ours: ARMOUR identifies, the PID runs the task
    controller, gains = add_controller(builder, arm, scenario, kind=spec.first_controller, connect=not switches)
    # The controller's certified bound (per-joint Kr; sigma_min from the armature lower bounds,
    # which identification never changes) is the tube the planner must respect.
    tracking = tracking_bounds_for(robot, gains.armour, box.lo)
    estimator = None
    if spec.identifies == methods.ESTIMATOR:
        # With a task phase the estimator stops at the switch: the task uses the box latched then.
        stop = task_switch_time_s(scenario, spec) if task else np.inf
        estimator = builder.AddSystem(make_estimator_system(robot, scenario, stop_time_s=stop, worker=worker))
        estimator.set_name("estimator")
        builder.Connect(arm.state_output, estimator.GetInputPort("state"))
        builder.Connect(arm.measured_torque_output, estimator.GetInputPort("measured_torque"))
        if arm.estimator_samples_output is not None:  # injected sample faults (scenario `faults`)
            builder.Connect(arm.estimator_samples_output, estimator.GetInputPort("samples"))
    theta_names = ("theta0", "theta_lower", "theta_upper")
    planner = desired_port = None
    if spec.uses_planner:
        plan_seed = scenario.seed if seed is None else seed
        planner, desired_port = _add_planner(
            builder, robot, scenario, spec, tracking, arm, (theta0, box), plan_seed, estimator, worker
        )
        excitation_thetas = [planner.GetOutputPort(f"plan_{name}") for name in theta_names]
    else:  # the Fourier excitation (identification after it, on its data), or no identification phase
        if spec.excitation is not None or not task:  # with a task, no excitation goes straight to it
            desired_port = _excitation_without_planner(builder, spec, robot, scenario)
        excitation_thetas = [_constant(builder, v, f"prior_{k}") for k, v in enumerate((theta0, box.lo, box.hi))]
    source, task_info = None, ()
    if task:
        task_info = task_plan(scenario)
        source = builder.AddSystem(
            make_task_source(
                robot,
                scenario,
                task_switch_time_s(scenario, spec),
                *task_info,
                arm.dumbbell,
                certify=spec.controller == "armour",  # ARMOUR runs the task: its certificate must hold
            )
        )
        source.set_name("task_phase_source")
        # Identification: the parameters the executing plan was certified with; task: the method's.
        if spec.model == methods.IDENTIFIED:
            task_thetas = [estimator.GetOutputPort(name) for name in theta_names]
        else:
            t0, tbox = parameter_sources.task_parameters(spec, robot, scenario)
            task_thetas = [_constant(builder, v, f"task_{k}") for k, v in enumerate((t0, tbox.lo, tbox.hi))]
        for name, excitation_port, task_port in zip(theta_names, excitation_thetas, task_thetas):
            if desired_port is not None:
                builder.Connect(excitation_port, source.GetInputPort(f"plan_{name}"))
            builder.Connect(task_port, source.GetInputPort(f"task_{name}"))
        if desired_port is not None:
            builder.Connect(desired_port, source.GetInputPort("plan_desired"))
        desired_port = source.GetOutputPort("desired")
        theta_ports = [source.GetOutputPort(name) for name in theta_names]
    else:
        theta_ports = excitation_thetas
    controllers = [controller]
    if switches:
        task_controller, _ = add_controller(builder, arm, scenario, kind=spec.controller, connect=False)
        task_controller.set_name("task_controller")
        controllers.append(task_controller)
    for ctrl in controllers:
        for name, port in zip(theta_names, theta_ports):
            builder.Connect(port, ctrl.GetInputPort(name))
        builder.Connect(desired_port, ctrl.GetInputPort("desired"))
    command = controller.GetOutputPort("torque")
    if switches:
        command = add_phase_switch(builder, arm, source, controllers)

    monitor = None if over_lcm else _add_monitor(builder, arm, robot, command)

    loggers = {
        "state": _add_logger(builder, arm.state_output, h, "state"),
        "measured_torque": _add_logger(builder, arm.measured_torque_output, h, "measured_torque"),
        "command": _add_logger(builder, command, h, "command"),
        "desired": _add_logger(builder, desired_port, h, "desired"),
    }
    if controller.HasOutputPort("diagnostics"):  # ARMOUR's [V_bar, h, lambda, |r|, |w_bar|]
        loggers["armour"] = _add_logger(builder, controller.GetOutputPort("diagnostics"), h, "armour")
    if controller.HasOutputPort("estimate"):  # what an adaptive controller identifies
        loggers["adaptive_estimate"] = _add_logger(builder, controller.GetOutputPort("estimate"), h, "estimate")
    visualizer = None
    if meshcat is not None:
        from safesysid.viz import add_visualizer

        visualizer = add_visualizer(builder, arm.query_output, meshcat)
    diagram = builder.Build()
    diagram.set_name(f"safesysid_{method}")
    return OnlineDiagram(
        diagram,
        arm,
        controller,
        planner,
        estimator,
        monitor,
        loggers,
        visualizer,
        meshcat,
        (theta0, box),
        tracking,
        source,
        task_info,
    )


def _add_monitor(builder, arm, robot, command):
    """The referee on the simulated station's own plant (links' geometry, torque before saturation)."""
    from safesysid.systems.plant.safety_monitor import SafetyMonitor

    ignore = [arm.released_body] if arm.released_body is not None else []
    h = arm.time_step
    monitor = builder.AddSystem(SafetyMonitor(arm.plant, arm.scene_graph, robot, period_s=h, ignore_bodies=ignore))
    monitor.set_name("safety_monitor")
    builder.Connect(arm.query_output, monitor.query_port)
    builder.Connect(arm.plant_state_output, monitor.state_port)
    builder.Connect(arm.motor_torque_output, monitor.torque_port)
    builder.Connect(command, monitor.command_port)
    return monitor


def _log(sink, context):
    data = sink.FindLog(context)
    return data.sample_times().copy(), data.data().T.copy()


def merge_events(*sources: Iterable[dict]) -> list[dict]:
    """One list of {t, kind, detail} from several systems' event lists, in time order (stable:
    events at the same instant keep their order within a source)."""
    return sorted((dict(e) for source in sources for e in source), key=lambda e: e["t"])


def run_online(
    scenario: Scenario,
    out_dir: str | Path,
    method: str | None = None,
    seed: int | None = None,
    live_meshcat: bool = False,
    write: bool = True,
) -> dict:
    """Run Algorithm 2 on a scenario; write summary.json, log.csv, plots, replay.html."""
    from pydrake.systems.analysis import Simulator
    from safesysid import figures, progress, report, viz
    from safesysid.joint_log import JointLog, write_joint_log
    from safesysid.systems.model.inertial import NAMES
    from safesysid.task_run import GuardedSimulator, judge, run_task_phase

    method = method or scenario.method
    seed = scenario.seed if seed is None else seed
    if write:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
    meshcat = viz.start_meshcat(live_meshcat) if write or live_meshcat else None
    wall0 = time.perf_counter()
    built = build_online(scenario, method, meshcat=meshcat, seed=seed)
    arm, robot = built.arm, built.arm.robot
    sim = GuardedSimulator(Simulator(built.diagram))
    progress.watch(
        sim.simulator, scenario, live_meshcat, getattr(getattr(built, "source", None), "switch_time_s", None)
    )
    ctx = sim.get_mutable_context()
    arm.seed_noise(ctx)
    arm.set_state(ctx, np.asarray(scenario.q0_rad, float))
    if built.visualizer is not None:
        built.visualizer.StartRecording()
    sim.Initialize()
    spec = methods.method_spec(method)
    # Without a task, a method without identification holds q0 as long as ours identifies.
    horizon = config.excitation_duration_s(spec, scenario) or config.planner_horizon_s(scenario)
    if built.source is None:
        # One step past the horizon so the estimator's update due at exactly t = horizon is applied.
        sim.AdvanceTo(horizon + scenario.plant.time_step_s)
        t_switch, sim_end, task_summary = np.inf, horizon, None
    else:
        t_switch = built.source.switch_time_s
        task_summary = run_task_phase(built, sim, scenario, method)
        sim_end = task_summary["end_time_s"]
    wall = time.perf_counter() - wall0

    t, state = _log(built.loggers["state"], ctx)
    _, tau_meas = _log(built.loggers["measured_torque"], ctx)
    _, command = _log(built.loggers["command"], ctx)
    _, desired = _log(built.loggers["desired"], ctx)
    n = robot.n
    q, v = state[:, :n], state[:, n:]
    error = desired[:, :n] - q
    cont = robot.joint_params.continuous
    error[:, cont] = np.angle(np.exp(1j * error[:, cont]))
    record = built.monitor.record(built.monitor.GetMyContextFromRoot(ctx))
    safety = record.summary()
    truth = arm.true_theta()[robot.ee_slice]
    est = built.estimator
    if est is not None:
        # The identification phase's estimate (the estimator keeps sampling in the task phase,
        # the payload's release included: nothing after the switch is the identification's).
        est_ctx = est.GetMyContextFromRoot(ctx)
        history = [h for h in est.history(est_ctx) if h["t"] <= t_switch]
        if history:
            theta_e0, lo, hi = (np.asarray(history[-1][k], float) for k in ("nominal", "lower", "upper"))
        else:
            theta_e0, lo, hi = est.final_estimate(est_ctx)
        cond_y = history[-1]["cond_Y"] if history else float("nan")
        update_times = [h["update_time_s"] for h in history]
        consistent = all(h["consistent"] for h in history)
        estimator_events = [e for e in est.events(est_ctx) if e["t"] <= t_switch]
        # the data-driven box before pruning and the paper's first-order interval, of that update
        extra_estimate = {k: history[-1][k] for k in ESTIMATE_EXTRA} if history else {}
    else:
        theta0, box = built.theta_prior
        theta_e0, lo, hi = theta0[robot.ee_slice], box.lo[robot.ee_slice], box.hi[robot.ee_slice]
        if spec.identifies == methods.ADAPTATION:  # the adaptive law's estimate, inside its projection box
            # its last value holding the payload: after the release the law adapts to the bare gripper
            t_est, adapted = _log(built.loggers["adaptive_estimate"], ctx)
            held = t_est < ((task_summary or {}).get("release_time_s") or np.inf)
            theta_e0 = adapted[held][-1] if held.any() else adapted[0]
        history, cond_y, update_times = [], float("nan"), []
        consistent, estimator_events = True, []
        extra_estimate = {}
    contains = bool(np.all((lo <= truth) & (truth <= hi)))
    plans, planner_events = [], []
    if built.planner is not None:
        planner_context = built.planner.GetMyContextFromRoot(ctx)
        plans, planner_events = built.planner.records(planner_context), built.planner.events(planner_context)
    task_events = task_summary.pop("events") if task_summary else []
    from safesysid.systems.plant.faults import scenario_events

    events = merge_events(  # every system's, in time order
        estimator_events,
        planner_events,
        task_events,
        arm.fault_events(ctx),
        scenario_events(scenario),
        [sim.failure] if sim.failure else [],
    )
    solve_times = [p["solve_time_s"] for p in plans]
    deadline = scenario.planner.replan_period_s
    bound = np.asarray(built.tracking.position, float)
    tracking_bound = float(np.max(bound))
    max_err = float(np.abs(error).max())
    ratio_t = np.max(np.abs(error) / bound, axis=1)  # per joint: Kr differs between joints
    worst_ratio = float(ratio_t.max())
    # The tube is ARMOUR's certificate: a PID or adaptive phase claims none, so is not judged on it.
    armour_active = np.where(np.asarray(t) < t_switch, spec.first_controller == "armour", spec.controller == "armour")
    failure, phase, t_fail = judge(
        record,
        plans,
        t,
        np.where(armour_active, ratio_t, 0.0),
        task_summary,
        t_switch,
        sim.failure["t"] if sim.failure else None,
    )
    robust = None
    if "armour" in built.loggers:
        _, diag = _log(built.loggers["armour"], ctx)
        robust = robust_input_summary(diag, armour_active, np.asarray(t) < t_switch)
    summary = {
        "scenario": scenario.name,
        "method": method,
        "seed": seed,
        "success": failure is None,
        "failure": failure,
        "phase": phase,
        "failure_time_s": t_fail,
        "collisions": safety["collisions"],
        "min_clearance_m": safety["min_clearance_m"],
        "max_torque_ratio": safety["max_torque_ratio"],
        "max_commanded_torque_ratio": safety["max_commanded_torque_ratio"],
        "max_joint_limit_ratio": safety["max_joint_limit_ratio"],
        "max_velocity_ratio": safety["max_velocity_ratio"],
        "max_tracking_error_rad": max_err,
        "tracking_bound_rad": tracking_bound,
        "max_tracking_error_ratio": worst_ratio,
        "tracking_bound_per_joint_rad": bound.tolist(),
        "placement_error_m": task_summary["placement"]["error_m"] if task_summary else None,
        "task": task_summary,
        "payload_true": {"theta": truth.tolist(), "dumbbell": arm.dumbbell.name if arm.dumbbell else None},
        "robot_parameters": scenario.plant.robot_parameters,  # the simulated arm's: nominal | drawn | corner (A1)
        "estimate": {
            "nominal": np.asarray(theta_e0).tolist(),
            "lower": np.asarray(lo).tolist(),
            "upper": np.asarray(hi).tolist(),
            "consistent": bool(consistent),
            **extra_estimate,
            "source": spec.identifies,  # estimator (Algorithm 1) | adaptation | none (the prior)
        },
        "events": events,
        "contains_truth": contains,
        "cond_Y": cond_y,
        "planner": {
            "iterations": len(plans),
            "solve_time_s": solve_times,
            "deadline_s": deadline,
            "missed_deadlines": int(sum(t_ > deadline for t_ in solve_times)),
            "brakes": sum(e["kind"] == "brake" for e in events),
            "solver": scenario.planner.solver if method != "random" else "random",
            "budget": scenario.planner.budget,  # iterations (deterministic) | wall_time (real time)
            "status": [p["status"] for p in plans],
            "cond_W": [p.get("cond") for p in plans],
            "refined": [p.get("refined", False) for p in plans],  # planner.point_refinement: certified on its own k
        },
        "sysid": {"updates": len(history), "update_time_s": update_times},
        "robust_input": robust,
        "wall_time_s": wall,
        "sim_time_s": float(sim_end),
    }
    if not write:
        return summary
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    extra = {f"qd{k + 1}": desired[:, k] for k in range(n)}
    extra.update({f"vd{k + 1}": desired[:, n + k] for k in range(n)})
    extra.update({f"ad{k + 1}": desired[:, 2 * n + k] for k in range(n)})
    extra.update({f"u{k + 1}": command[:, k] for k in range(n)})
    # The end-effector estimate in force at each sample: the prior until the first update.
    theta0, box = built.theta_prior
    first = [theta0[robot.ee_slice], box.lo[robot.ee_slice], box.hi[robot.ee_slice]]
    times = np.array([h["t"] for h in history])
    idx = np.searchsorted(times, t, side="right") - 1
    for j, (key, name) in enumerate((("nominal", ""), ("lower", "_lo"), ("upper", "_hi"))):
        vals = np.array([first[j]] + [h[key] for h in history])
        for k, pname in enumerate(NAMES):
            extra[f"est_{pname}{name}"] = vals[idx + 1, k]
    write_joint_log(out / "log.csv", JointLog(t, q, v, tau_meas), extra)
    rec = record
    report.plot_tracking(
        out / "tracking.png",
        t,
        error,
        built.tracking.position,
        np.max(np.abs(command) / robot.joint_params.torque_limit, 1),
    )
    phases = figures.phases_of(summary)
    report.plot_clearance(out / "clearance.png", np.array(rec.times), np.array(rec.clearance), phases)
    figures.write_run_figures(out, summary, history, robot.joint_params.torque_limit)  # joints, conditioning
    # The identified body is the last link + gripper + payload: say so, and show the prior behind the intervals.
    body = report.identified_body_text(
        truth[0], *((arm.dumbbell.name, arm.dumbbell.mass_kg) if arm.dumbbell else ("", None))
    )
    prior = (first[1], first[2])
    title = f"{scenario.name} / {method}; {body}"
    report.plot_intervals(out / "intervals.png", theta_e0, lo, hi, truth, title=title, prior=prior)
    if history:
        report.plot_estimate_history(
            out / "mass.png",
            [0.0] + [h["t"] for h in history],
            [first[0]] + [h["nominal"] for h in history],
            [first[1]] + [h["lower"] for h in history],
            [first[2]] + [h["upper"] for h in history],
            truth,
            prior=prior,
            title=body,
        )
    # After the release the welded payload is empty (no mass, no collision) but still drawn: hide it.
    released = [e["t"] for e in summary["events"] if e["kind"] == "release"]
    hidden = [(viz.body_path(arm.payload_frame_name()), released[0])] if released else []
    replay = viz.ReplayScene(robot, t, q, desired[:, :n], figures.phases_of(summary), scenario.obstacles, hidden)
    viz.decorate(meshcat, built.visualizer, replay)
    if built.visualizer is not None:
        if built.planner is not None:
            draw_plans(meshcat, robot, built.planner.results(built.planner.GetMyContextFromRoot(ctx)))
        viz.save_replay(meshcat, built.visualizer, out / "replay.html")
    viz.add_phase_banner(out / "replay.html", replay.phases)
    return summary


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
            viz.draw_swept_spheres(meshcat, res.details["sphere_centres"], res.details["sphere_radii"], index)
