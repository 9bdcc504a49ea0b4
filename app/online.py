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

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from safesysid.online_diagram import THETA_NAMES, OnlineDiagram
from safesysid.summary import SimulatedRun, read_logs, summarize
from safesysid.systems import config, methods
from safesysid.systems.config import Scenario, ScenarioError, task_enabled
from safesysid.systems.model import parameter_sources
from safesysid.systems.model.loading import robot_from_scenario

if TYPE_CHECKING:
    from pydrake.geometry import Meshcat
    from pydrake.systems.framework import OutputPort
    from pydrake.systems.primitives import VectorLogSink
    from safesysid.progress import RunDisplay
    from safesysid.systems.controller.armour import TrackingBounds
    from safesysid.systems.estimation.system import SysIdEstimator
    from safesysid.systems.hardware.background import BackgroundWorker
    from safesysid.systems.math.intervals import Interval
    from safesysid.systems.model.payload import Dumbbell
    from safesysid.systems.model.robot_model import RobotModel
    from safesysid.systems.planner.system import ExcitingPlanner
    from safesysid.systems.plant.arm_plant import RealArm


def prior(robot: RobotModel, scenario: Scenario, method: str) -> tuple[np.ndarray, Interval]:
    """(theta0, [theta]) the controller and planner start from (parameter_sources.initial_parameters:
    Table II before an identification phase; "wrong", "grav-pid": the bare end effector, zero width)."""
    return parameter_sources.initial_parameters(methods.method_spec(method), robot, scenario)


def _add_logger(builder, port, period, name):
    from pydrake.systems.primitives import LogVectorOutput

    sink = LogVectorOutput(port, builder, period)
    sink.set_name(f"log_{name}")
    return sink


def _add_planner(builder, built: OnlineDiagram, scenario: Scenario, spec, *, seed: int, worker=None):
    """Algorithm 2's planner as the method's excitation, fed by the estimator (or the prior when
    the method does not identify with it). Returns (planner, desired-trajectory port)."""
    from pydrake.systems.primitives import Multiplexer

    robot, estimator, theta_prior = built.arm.robot, built.estimator, built.theta_prior
    trajectory = spec.excitation.trajectory
    system = make_planner_system(
        robot,
        scenario,
        trajectory,
        tracking=built.tracking,
        dumbbell=built.arm.dumbbell,
        theta_prior=theta_prior,
        seed=seed,
        worker=worker,
    )
    planner = builder.AddNamedSystem("planner", system)
    desired = builder.AddNamedSystem("desired_q_v_a", Multiplexer([robot.n] * 3))
    for k, name in enumerate(("q_desired", "v_desired", "a_desired")):
        builder.Connect(planner.GetOutputPort(name), desired.get_input_port(k))
    theta0, box = theta_prior
    for k, (name, value) in enumerate(zip(THETA_NAMES, (theta0, box.lo, box.hi))):
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

        source = builder.AddNamedSystem(
            "fourier_excitation", FourierSource(fourier_excitation(robot, scenario).trajectory)
        )
        return source.get_output_port()
    q0 = np.asarray(scenario.q0_rad, float)
    return _constant(builder, np.concatenate([q0, np.zeros(2 * robot.n)]), "hold_q0")


def _constant(builder, value, name):
    from pydrake.systems.primitives import ConstantVectorSource

    return builder.AddNamedSystem(name, ConstantVectorSource(np.asarray(value, float))).get_output_port()


def make_planner_system(
    robot: RobotModel,
    scenario: Scenario,
    trajectory: str,
    *,
    tracking: TrackingBounds,
    dumbbell: Dumbbell | None,
    theta_prior: tuple[np.ndarray, Interval],
    seed: int,
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


def task_switch_time_s(scenario: Scenario, spec: methods.MethodSpec, *, wall_clock: bool = False) -> float:
    """Start of the task phase: one plant step after the identification phase (so the
    estimator's update due at its end is in the latched box), or 0 without identification.
    wall_clock: one t_p later, when that update comes back from the worker (background.py)."""
    if spec.excitation is None:
        return 0.0
    late = scenario.planner.replan_period_s if wall_clock else 0.0
    return config.excitation_duration_s(spec, scenario) + late + scenario.plant.time_step_s


def make_estimator_system(
    robot: RobotModel,
    scenario: Scenario,
    update_period_s: float | None = None,
    *,
    stop_time_s: float = np.inf,
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
        step_period_s=config.loop_step_s(scenario),
        **extra,
    )


@dataclass
class _Excitation:
    """The identification phase's desired-trajectory port (None: none, the task starts at once)
    and the (theta0, lower, upper) ports of the parameters its plans were certified with."""

    planner: ExcitingPlanner | None
    desired: OutputPort | None
    thetas: list[OutputPort]


def _add_arm(
    builder, scenario: Scenario, robot: RobotModel, *, seed: int | None, task: bool, true_scenario: Scenario | None
) -> RealArm:
    """The simulated station, or the arm over LCM (systems/hardware/lcm_arm.py). true_scenario: the
    simulated arm's own robot, payload and plant effects; the systems above it read arm.robot, the
    model `scenario` gives them."""
    from safesysid.systems.plant.station import add_real_arm

    if scenario.arm.driver == "lcm":
        from safesysid.systems.hardware.lcm_arm import add_lcm_arm, make_lcm

        return add_lcm_arm(builder, scenario, robot, lcm=make_lcm(scenario))
    releasable = task and not scenario.task.goal_q_rad
    if true_scenario is None:
        return add_real_arm(builder, scenario, robot=robot, seed=seed, releasable=releasable)
    arm = add_real_arm(builder, true_scenario, seed=seed, releasable=releasable)
    return dataclasses.replace(arm, robot=robot)


def _add_estimator(builder, arm: RealArm, scenario: Scenario, *, stop_time_s: float, worker) -> SysIdEstimator:
    estimator = builder.AddNamedSystem(
        "estimator", make_estimator_system(arm.robot, scenario, stop_time_s=stop_time_s, worker=worker)
    )
    builder.Connect(arm.state_output, estimator.GetInputPort("state"))
    builder.Connect(arm.measured_torque_output, estimator.GetInputPort("measured_torque"))
    if arm.estimator_samples_output is not None:  # injected sample faults (scenario `faults`)
        builder.Connect(arm.estimator_samples_output, estimator.GetInputPort("samples"))
    return estimator


def _add_excitation(
    builder, built: OnlineDiagram, scenario: Scenario, spec, *, seed, task: bool, worker
) -> _Excitation:
    """The method's identification phase: Algorithm 2's planner, the Fourier trajectory, holding
    q0, or (no excitation, with a task) nothing."""
    theta0, box = built.theta_prior
    if spec.uses_planner:
        plan_seed = scenario.seed if seed is None else seed
        planner, desired = _add_planner(builder, built, scenario, spec, seed=plan_seed, worker=worker)
        return _Excitation(planner, desired, [planner.GetOutputPort(f"plan_{name}") for name in THETA_NAMES])
    # the Fourier excitation (identification after it, on its data), or no identification phase
    desired = None
    if spec.excitation is not None or not task:  # with a task, no excitation goes straight to it
        desired = _excitation_without_planner(builder, spec, built.arm.robot, scenario)
    return _Excitation(
        None, desired, [_constant(builder, v, f"prior_{k}") for k, v in enumerate((theta0, box.lo, box.hi))]
    )


def _add_task_phase(
    builder, built: OnlineDiagram, scenario: Scenario, spec, *, excitation: _Excitation, worker
) -> tuple:
    """The TaskPhaseSource between the excitation and the controller. Returns (source, (problem,
    plan), desired port, theta ports): identification: the parameters the executing plan was
    certified with; task: the method's. worker: the wall-clock run's (the task is made there)."""
    from safesysid.systems.task.phase import task_plan
    from safesysid.task_run import make_task_source

    robot = built.arm.robot
    task_info = task_plan(scenario)
    switch_s = task_switch_time_s(scenario, spec, wall_clock=worker is not None)
    certify = spec.controller == "armour"  # ARMOUR runs the task: its certificate must hold
    source = builder.AddNamedSystem(
        "task_phase_source",
        make_task_source(
            robot,
            scenario,
            switch_s,
            problem=task_info[0],
            plan=task_info[1],
            held=built.arm.dumbbell,
            certify=certify,
            worker=worker,
        ),
    )
    if spec.model == methods.IDENTIFIED:
        task_thetas = [built.estimator.GetOutputPort(name) for name in THETA_NAMES]
    else:
        t0, tbox = parameter_sources.task_parameters(spec, robot, scenario)
        task_thetas = [_constant(builder, v, f"task_{k}") for k, v in enumerate((t0, tbox.lo, tbox.hi))]
    for name, excitation_port, task_port in zip(THETA_NAMES, excitation.thetas, task_thetas):
        if excitation.desired is not None:
            builder.Connect(excitation_port, source.GetInputPort(f"plan_{name}"))
        builder.Connect(task_port, source.GetInputPort(f"task_{name}"))
    if excitation.desired is not None:
        builder.Connect(excitation.desired, source.GetInputPort("plan_desired"))
    theta_ports = [source.GetOutputPort(name) for name in THETA_NAMES]
    return source, task_info, source.GetOutputPort("desired"), theta_ports


def _connect_controllers(builder, built: OnlineDiagram, scenario: Scenario, spec, *, desired, thetas, switches: bool):
    """The parameters and desired trajectory into the controller (and the task controller of a
    method that switches). Returns the commanded torque port."""
    from safesysid.closed_loop import add_controller, add_phase_switch

    controllers = [built.controller]
    if switches:
        task_controller, _ = add_controller(
            builder, built.arm, scenario, kind=spec.controller, connect=False, name="task_controller"
        )
        controllers.append(task_controller)
    for ctrl in controllers:
        for name, port in zip(THETA_NAMES, thetas):
            builder.Connect(port, ctrl.GetInputPort(name))
        builder.Connect(desired, ctrl.GetInputPort("desired"))
    if switches:
        return add_phase_switch(builder, built.arm, built.source, controllers=controllers)
    return built.controller.GetOutputPort("torque")


def _send_plans(builder, built: OnlineDiagram, scenario: Scenario, *, switches: bool) -> None:
    """`arm.control_loop: arm`: the controller runs beside the arm on the plans sent to it; here
    nothing evaluates it (no command, no command logger). Returns the command port: None."""
    from safesysid.systems.hardware.lcm_arm import add_plan_sender

    if built.planner is None:
        raise ScenarioError(
            "arm.control_loop: arm needs a method that plans (ours, random): plans are what crosses "
            "(arm.control_loop: run drives the arm with torques)"
        )
    if switches:
        raise ScenarioError(
            "arm.control_loop: arm runs one controller, not a method that switches it for the task "
            "(arm.control_loop: run drives the arm with torques)"
        )
    plans = built.planner.GetOutputPort("plan")
    sender = add_plan_sender(builder, scenario, built.planner, plans, lcm=built.arm.lcm)
    if built.source is not None:  # the task's curves cross as plans too
        builder.Connect(built.source.GetOutputPort("phase_state"), sender.task)
    built.arm.plan_sender = sender


def _add_loggers(builder, built: OnlineDiagram, *, command, desired, h: float) -> dict[str, VectorLogSink]:
    """command None: the controller is beside the arm (its torque and diagnostics are the arm's)."""
    arm, controller = built.arm, built.controller
    loggers = {
        "state": _add_logger(builder, arm.state_output, h, "state"),
        "measured_torque": _add_logger(builder, arm.measured_torque_output, h, "measured_torque"),
        "desired": _add_logger(builder, desired, h, "desired"),
    }
    if command is None:
        return loggers
    loggers["command"] = _add_logger(builder, command, h, "command")
    if controller.HasOutputPort("diagnostics"):  # ARMOUR's [V_bar, h, lambda, |r|, |w_bar|]
        loggers["armour"] = _add_logger(builder, controller.GetOutputPort("diagnostics"), h, "armour")
    if controller.HasOutputPort("estimate"):  # what an adaptive controller identifies
        loggers["adaptive_estimate"] = _add_logger(builder, controller.GetOutputPort("estimate"), h, "estimate")
    return loggers


def build_online(
    scenario: Scenario,
    method: str | None = None,
    meshcat: Meshcat | None = None,
    *,
    seed: int | None = None,
    worker: BackgroundWorker | None = None,
    true_scenario: Scenario | None = None,
) -> OnlineDiagram:
    """worker: the wall-clock run's (app/online_lcm.py): planner and estimator calls run in it.
    scenario.arm.driver lcm: the arm is reached over LCM (systems/hardware/lcm_arm.py); the
    referee and the payload's release are the arm's (no SafetyMonitor here; the task phase asks
    the arm's gripper to release, app/task_lcm.py).
    true_scenario: a simulated arm other than the models' (a sim-to-real study: the models above
    the plant from `scenario`, e.g. a corrected model; the arm, its payload and hidden effects from
    true_scenario); None: the scenario's own."""
    from pydrake.systems.framework import DiagramBuilder
    from safesysid.closed_loop import add_controller
    from safesysid.systems.controller.armour import tracking_bounds_for

    method = method or scenario.method
    spec = methods.method_spec(method)
    robot = robot_from_scenario(scenario)
    over_lcm = scenario.arm.driver == "lcm"
    task = task_enabled(scenario)
    builder = DiagramBuilder()
    arm = _add_arm(builder, scenario, robot, seed=seed, task=task, true_scenario=true_scenario)
    theta0, box = prior(robot, scenario, method)
    switches = task and spec.switches_controller  # grav-pid-ours: ARMOUR identifies, the PID runs the task
    beside_arm = over_lcm and scenario.arm.control_loop == "arm"  # the arm runs it: here it is never evaluated
    controller, gains = add_controller(
        builder, arm, scenario, kind=spec.first_controller, connect=not (switches or beside_arm)
    )
    # The controller's certified bound (per-joint Kr; sigma_min from the armature lower bounds,
    # which identification never changes) is the tube the planner must respect.
    tracking = tracking_bounds_for(robot, gains.armour, box.lo)
    built = OnlineDiagram(arm=arm, controller=controller, meshcat=meshcat, theta_prior=(theta0, box), tracking=tracking)
    if spec.identifies == methods.ESTIMATOR:
        # With a task phase the estimator stops at the switch: the task uses the box latched then.
        stop = task_switch_time_s(scenario, spec, wall_clock=worker is not None) if task else np.inf
        built.estimator = _add_estimator(builder, arm, scenario, stop_time_s=stop, worker=worker)
    excitation = _add_excitation(builder, built, scenario, spec, seed=seed, task=task, worker=worker)
    built.planner = excitation.planner
    desired, thetas = excitation.desired, excitation.thetas
    if task:
        built.source, built.task, desired, thetas = _add_task_phase(
            builder, built, scenario, spec, excitation=excitation, worker=worker
        )
    command = _connect_controllers(builder, built, scenario, spec, desired=desired, thetas=thetas, switches=switches)
    if beside_arm:
        command = _send_plans(builder, built, scenario, switches=switches)
    built.monitor = None if over_lcm else _add_monitor(builder, arm, robot, command)
    built.loggers = _add_loggers(builder, built, command=command, desired=desired, h=config.loop_step_s(scenario))
    if meshcat is not None and over_lcm:  # the live arm from the received status (app/lcm_view.py)
        from safesysid.lcm_view import add_status_view

        built.visualizer = add_status_view(builder, arm.state_output, robot, scenario, meshcat).visualizer
    elif meshcat is not None:
        from safesysid.viz import add_visualizer

        built.visualizer = add_visualizer(builder, arm.query_output, meshcat)
    built.diagram = builder.Build()
    built.diagram.set_name(f"safesysid_{method}")
    return built


def _add_monitor(builder, arm, robot, command):
    """The referee on the simulated station's own plant (links' geometry, torque before saturation)."""
    from safesysid.systems.plant.safety_monitor import SafetyMonitor

    ignore = [arm.released_body] if arm.released_body is not None else []
    h = arm.time_step
    monitor = builder.AddNamedSystem(
        "safety_monitor", SafetyMonitor(arm.plant, arm.scene_graph, robot, period_s=h, ignore_bodies=ignore)
    )
    builder.Connect(arm.query_output, monitor.query_port)
    builder.Connect(arm.plant_state_output, monitor.state_port)
    builder.Connect(arm.motor_torque_output, monitor.torque_port)
    builder.Connect(command, monitor.command_port)
    return monitor


def simulate(built: OnlineDiagram, scenario: Scenario, method: str, *, live_meshcat: RunDisplay | bool) -> SimulatedRun:
    """Advance a built run from rest at q0 through identification (and the task phase, the
    release and the settling when the scenario has one)."""
    from pydrake.systems.analysis import Simulator
    from safesysid import progress
    from safesysid.task_run import GuardedSimulator, run_task_phase

    arm = built.arm
    sim = GuardedSimulator(Simulator(built.diagram))
    progress.watch(sim.simulator, scenario, live_meshcat, switch_time_s=getattr(built.source, "switch_time_s", None))
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
        return SimulatedRun(sim, ctx, np.inf, horizon, None)
    task_summary = run_task_phase(built, sim, scenario, method=method)
    return SimulatedRun(sim, ctx, built.source.switch_time_s, task_summary["end_time_s"], task_summary)


def run_online(
    scenario: Scenario,
    out_dir: str | Path | None,
    method: str | None = None,
    *,
    seed: int | None = None,
    live_meshcat: RunDisplay | bool = False,
    write: bool = True,
    true_scenario: Scenario | None = None,
) -> dict:
    """Run Algorithm 2 on a scenario: build -> simulate -> summarize -> write (summary.json,
    log.csv, plots, replay.html; nothing without `write`). Returns summary.json's dict.
    true_scenario: the simulated arm's own scenario (build_online)."""
    from safesysid import viz
    from safesysid.outputs import write_outputs

    method = method or scenario.method
    seed = scenario.seed if seed is None else seed
    if write:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
    meshcat = viz.start_meshcat(live_meshcat) if write or live_meshcat else None
    wall0 = time.perf_counter()
    built = build_online(scenario, method, meshcat=meshcat, seed=seed, true_scenario=true_scenario)
    run = simulate(built, scenario, method, live_meshcat=live_meshcat)
    wall_s = time.perf_counter() - wall0
    logs = read_logs(built, run.context)
    summary, identified = summarize(built, run, logs, scenario=scenario, method=method, seed=seed, wall_s=wall_s)
    summary = summary.to_json()
    if write:
        write_outputs(out, built, logs, summary=summary, ident=identified, scenario=scenario, context=run.context)
    return summary
