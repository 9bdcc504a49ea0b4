"""Closed loop for tests, benchmarks and the run command: the real arm station <- a controller
(systems/controller/systems.py) <- one fixed trajectory, with fixed theta0 / [theta] (the online
diagram, with planner and estimator, is app/online.py)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem, OutputPort
from pydrake.systems.primitives import ConstantVectorSource, LogVectorOutput, VectorLogSink
from safesysid.systems.controller import systems as controller_systems
from safesysid.systems.math.intervals import Interval
from safesysid.systems.planner.trajectory_source import Piece, make_trajectory_source
from safesysid.systems.plant.arm_plant import RealArm
from safesysid.systems.plant.station import add_real_arm

if TYPE_CHECKING:
    from safesysid.systems.config import Scenario
    from safesysid.systems.controller.systems import ControllerBase, ControllerGains
    from safesysid.systems.math.bezier import QuinticBezier
    from safesysid.systems.model.payload import Dumbbell
    from safesysid.systems.model.robot_model import RobotModel
    from safesysid.systems.planner.trajectory_source import TaskPhaseSource


def add_controller(
    builder: DiagramBuilder,
    arm: RealArm,
    scenario: Scenario,
    *,
    kind: str | None = None,
    connect: bool = True,
    name: str = "controller",
) -> tuple[ControllerBase, ControllerGains]:
    """The scenario's controller (scenario.controller.kind unless `kind`) closing the loop on the
    arm station: station state -> controller -> commanded torque (unless not `connect`: the
    caller routes the torque). Its inputs desired, theta0, theta_lower, theta_upper are the
    caller's to connect. Returns (controller, gains)."""
    robot = arm.robot
    gains = controller_systems.gains_from_scenario(scenario, robot.n)
    ctrl = builder.AddNamedSystem(
        name,
        controller_systems.make_controller(
            kind or scenario.controller.kind, robot, gains, time_step=scenario.plant.time_step_s
        ),
    )
    builder.Connect(arm.state_output, ctrl.GetInputPort("state"))
    if connect:
        builder.Connect(ctrl.GetOutputPort("torque"), arm.commanded_torque_input)
    return ctrl, gains


def add_phase_switch(
    builder: DiagramBuilder, arm: RealArm, source: TaskPhaseSource, *, controllers: list[ControllerBase]
) -> OutputPort:
    """The commanded torque of a method whose task controller differs from its identification
    controller: controllers[0] until the TaskPhaseSource `source` switches, controllers[1] after.
    Returns the selected torque port (the one the referee judges), already driving the arm."""
    switch = builder.AddNamedSystem("controller_by_phase", controller_systems.PhaseSwitch(arm.robot.n))
    builder.Connect(source.GetOutputPort("phase"), switch.GetInputPort("phase"))
    for name, ctrl in zip(("identification", "task"), controllers):
        builder.Connect(ctrl.GetOutputPort("torque"), switch.GetInputPort(name))
    builder.Connect(switch.GetOutputPort("torque"), arm.commanded_torque_input)
    return switch.GetOutputPort("torque")


@dataclass
class ClosedLoop:
    diagram: Diagram
    arm: RealArm
    controller: ControllerBase
    source: LeafSystem  # trajectory_source.make_trajectory_source
    loggers: dict[str, VectorLogSink]  # state, desired, torque, measured_torque, diagnostics


def build_closed_loop(
    scenario: Scenario,
    trajectory: tuple[QuinticBezier, np.ndarray] | list[Piece],
    theta0: ArrayLike,
    *,
    theta_box: Interval,
    kind: str | None = None,
    robot: RobotModel | None = None,
    dumbbell: Dumbbell | str | None = "scenario",
    log: bool = True,
    seed: int | None = None,
) -> ClosedLoop:
    """Real arm + controller (scenario.controller.kind unless `kind`) + trajectory source, with
    fixed theta0 / [theta] (an estimator can be connected instead by building by hand)."""
    builder = DiagramBuilder()
    arm = add_real_arm(builder, scenario, robot=robot, dumbbell=dumbbell, seed=seed)
    h = scenario.plant.time_step_s
    ctrl, _ = add_controller(builder, arm, scenario, kind=kind)
    src = builder.AddNamedSystem("trajectory_source", make_trajectory_source(arm.n, trajectory))
    builder.Connect(src.get_output_port(), ctrl.GetInputPort("desired"))
    for name, value in (("theta0", theta0), ("theta_lower", theta_box.lo), ("theta_upper", theta_box.hi)):
        const = builder.AddNamedSystem(name, ConstantVectorSource(np.asarray(value, float)))
        builder.Connect(const.get_output_port(), ctrl.GetInputPort(name))
    loggers = {}
    if log:
        outputs = {
            "state": arm.state_output,
            "desired": src.get_output_port(),
            "torque": ctrl.GetOutputPort("torque"),
            "measured_torque": arm.measured_torque_output,
        }
        if ctrl.HasOutputPort("diagnostics"):
            outputs["diagnostics"] = ctrl.GetOutputPort("diagnostics")
        for name, port in outputs.items():
            loggers[name] = LogVectorOutput(port, builder, h)
            loggers[name].set_name(f"log_{name}")
    return ClosedLoop(builder.Build(), arm, ctrl, src, loggers)


def simulate_closed_loop(
    loop: ClosedLoop, q0: ArrayLike, duration_s: float, *, v0: ArrayLike | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Run from (q0, v0); returns {name: (t, data (N, size))} from the loggers."""
    sim = Simulator(loop.diagram)
    ctx = sim.get_mutable_context()
    loop.arm.seed_noise(ctx)
    loop.arm.set_state(ctx, q0, v0)
    sim.Initialize()
    sim.AdvanceTo(duration_s)
    out = {}
    for name, sink in loop.loggers.items():
        data = sink.FindLog(ctx)
        out[name] = (data.sample_times().copy(), data.data().T.copy())
    return out
