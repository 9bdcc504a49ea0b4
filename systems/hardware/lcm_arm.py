"""The arm station over LCM (the Drake hardware idiom: MakeHardwareStation(..., hardware=True)).

add_lcm_arm: the run's side. The same ports as systems/plant/station.py's station (commanded_torque in;
state, measured_torque, arm-timestamped estimator samples out) implemented by LCM subscriber and
publisher systems behind one LcmInterfaceSystem; nothing else in the run's diagram changes.
add_arm_driver: the arm's side (`safesysid arm-sim`, the reference a hardware driver follows):
commands into the simulated station's commanded_torque, its status out, the watchdog between.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from drake import lcmt_panda_command, lcmt_panda_status
from safesysid.systems.estimation.packets import PACKET_ROWS

from ..config import loop_step_s
from .lcm_systems import ArmDriver, CommandEncoder, LatestMessage, StatusEncoder, StatusReceiver
from .queued_lcm import QueuedLcm

if TYPE_CHECKING:
    from pydrake.lcm import DrakeLcm
    from pydrake.systems.framework import Context, DiagramBuilder, InputPort, OutputPort
    from safesysid.systems.model.payload import Dumbbell
    from safesysid.systems.model.robot_model import RobotModel
    from safesysid.systems.plant.arm_plant import RealArm

    from ..config import Scenario
    from .background import WallClockPlanner
    from .plan_follower import PlanFollower
    from .plan_sender import PlanSender

# The run waits this long at initialization for the arm's first status (an arm must be answering).
FIRST_STATUS_TIMEOUT_S = 10.0


def make_lcm(scenario: Scenario) -> DrakeLcm:
    from pydrake.lcm import DrakeLcm

    return DrakeLcm(scenario.arm.lcm_url)


def add_lcm_interface(builder: DiagramBuilder, lcm: DrakeLcm) -> None:
    """The LcmInterfaceSystem that pumps `lcm` for the diagram's publishers."""
    from pydrake.systems.lcm import LcmInterfaceSystem

    builder.AddSystem(LcmInterfaceSystem(lcm)).set_name("lcm_interface")


@dataclass
class LcmArm:
    """The run's view of an arm reached over LCM: RealArm's ports, without the plant (the
    referee, the ground truth and the payload's release live on the arm's side)."""

    robot: RobotModel
    dumbbell: Dumbbell | None  # the scenario's payload: what the planner assumes it carries
    commanded_torque_input: InputPort | None  # None: the controller is beside the arm (arm.control_loop)
    state_output: OutputPort
    measured_torque_output: OutputPort
    estimator_samples_output: OutputPort
    hold_output: OutputPort
    receiver: StatusReceiver
    statuses: LatestMessage
    lcm: DrakeLcm
    command_channel: str
    time_step: float
    released_body: None = None
    plant: None = None
    plan_sender: PlanSender | None = None  # arm.control_loop arm: the plans go to the arm's controller

    def fault_events(self, context: Context) -> list[dict]:
        return list(self.receiver.guard(self.receiver.GetMyContextFromRoot(context)).events)


def add_lcm_arm(builder: DiagramBuilder, scenario: Scenario, robot: RobotModel, *, lcm: DrakeLcm) -> LcmArm:
    from safesysid.systems.plant.arm_plant import scenario_dumbbell

    n, h, cfg = robot.n, scenario.plant.time_step_s, scenario.arm
    add_lcm_interface(builder, lcm)
    # Every status, not one per step (queued_lcm.py); the receiver hands them over at its step.
    # The controller beside the arm (arm.control_loop): no torque crosses, and a status outage is a
    # gap in the estimator's samples, not a hold.
    beside = cfg.control_loop == "arm"
    statuses = LatestMessage(QueuedLcm(cfg.lcm_url), cfg.status_channel, lcmt_panda_status, backlog=4 * PACKET_ROWS)
    receiver = builder.AddSystem(
        StatusReceiver(
            n,
            statuses,
            loop_step_s(scenario),
            status_timeout_s=cfg.status_timeout_ms * 1e-3,
            q_start=np.asarray(scenario.q0_rad),
            resume=beside,
        )
    )
    receiver.set_name("status_receiver")
    return LcmArm(
        robot=robot,
        dumbbell=scenario_dumbbell(scenario),
        commanded_torque_input=None if beside else _add_command_path(builder, receiver, cfg, n, h, lcm),
        state_output=receiver.GetOutputPort("state"),
        measured_torque_output=receiver.GetOutputPort("measured_torque"),
        estimator_samples_output=receiver.GetOutputPort("samples"),
        hold_output=receiver.GetOutputPort("hold"),
        receiver=receiver,
        statuses=statuses,
        lcm=lcm,
        command_channel=cfg.command_channel,
        time_step=h,
    )


def _add_command_path(builder, receiver: StatusReceiver, cfg, n: int, h: float, lcm: DrakeLcm) -> InputPort:
    """u -> lcmt_panda_command every step (the controller in the run); its torque input."""
    from pydrake.systems.lcm import LcmPublisherSystem

    encoder = builder.AddSystem(CommandEncoder(n))
    encoder.set_name("command_encoder")
    builder.Connect(receiver.GetOutputPort("hold"), encoder.hold)
    # From the first step on, not at Initialize: the arm's watchdog counts from the first command,
    # and the run's set-up after Initialize (the controller's kernels, the collector) takes longer.
    pub = builder.AddSystem(
        LcmPublisherSystem.Make(cfg.command_channel, lcmt_panda_command, lcm, publish_period=h, publish_offset=h)
    )
    pub.set_name("command_publisher")
    builder.Connect(encoder.get_output_port(), pub.get_input_port())
    return encoder.torque


def add_plan_sender(
    builder: DiagramBuilder, scenario: Scenario, planner: WallClockPlanner, plan_port: OutputPort, *, lcm: DrakeLcm
) -> PlanSender:
    """The run side of `arm.control_loop: arm`: each certified plan to arm.plan_channel (plan_sender.py)."""
    from .plan_sender import PlanSender

    cfg = scenario.arm
    sender = builder.AddSystem(PlanSender(planner, lcm, cfg.plan_channel, lead_s=cfg.plan_lead_ms * 1e-3))
    sender.set_name("plan_sender")
    builder.Connect(plan_port, sender.get_input_port(0))
    return sender


def add_arm_driver(builder: DiagramBuilder, arm: RealArm, scenario: Scenario, *, lcm: DrakeLcm) -> ArmDriver:
    """Commands -> ArmDriver (watchdog, hold) -> the station's commanded_torque; its status out
    every plant step. Returns the driver (its torque output is u before saturation: the referee's)."""
    cfg, h = scenario.arm, scenario.plant.time_step_s
    add_lcm_interface(builder, lcm)
    commands = LatestMessage(QueuedLcm(cfg.lcm_url), cfg.command_channel, lcmt_panda_command)  # the newest of a step's
    q_start = np.asarray(scenario.q0_rad, float)
    driver = builder.AddSystem(
        ArmDriver(
            arm.robot.n, plant_gravity(arm), commands, time_step_s=h, watchdog_s=cfg.watchdog_ms * 1e-3, q_start=q_start
        )
    )
    driver.set_name("arm_driver")
    builder.Connect(arm.state_output, driver.state)
    builder.Connect(driver.get_output_port(), arm.commanded_torque_input)
    add_status_publisher(builder, arm, scenario, lcm=lcm, commanded_torque=driver.get_output_port())
    return driver


def add_plan_follower(
    builder: DiagramBuilder, scenario: Scenario, *, n: int, prior: tuple, released: tuple | None = None
) -> PlanFollower:
    """The arm side of `arm.control_loop: arm`: the plans of arm.plan_channel, evaluated at the
    arm's clock, for a controller beside the arm (its desired and parameter inputs; `released`:
    its parameters once the payload is let go)."""
    from drake import lcmt_drake_signal

    from .plan_follower import PlanFollower

    cfg = scenario.arm
    plans = LatestMessage(QueuedLcm(cfg.lcm_url), cfg.plan_channel, lcmt_drake_signal, backlog=64)
    follower = PlanFollower(
        n,
        plans,
        time_step_s=scenario.plant.time_step_s,
        q_start=np.asarray(scenario.q0_rad, float),
        prior=prior,
        released=released,
    )
    follower.set_name("plan_follower")
    return builder.AddSystem(follower)


def add_status_publisher(
    builder: DiagramBuilder, arm: RealArm, scenario: Scenario, *, lcm: DrakeLcm, commanded_torque: OutputPort
) -> None:
    """The arm's status (encoders, torque sensor, the torque applied before saturation) every plant step."""
    from pydrake.systems.lcm import LcmPublisherSystem

    encoder = builder.AddSystem(StatusEncoder(arm.robot.n))
    encoder.set_name("status_encoder")
    builder.Connect(arm.state_output, encoder.state)
    builder.Connect(arm.measured_torque_output, encoder.measured_torque)
    builder.Connect(commanded_torque, encoder.commanded_torque)
    cfg, h = scenario.arm, scenario.plant.time_step_s
    pub = builder.AddSystem(LcmPublisherSystem.Make(cfg.status_channel, lcmt_panda_status, lcm, publish_period=h))
    pub.set_name("status_publisher")
    builder.Connect(encoder.get_output_port(), pub.get_input_port())


def plant_gravity(arm: RealArm) -> Callable[[np.ndarray], np.ndarray]:
    """q -> the torque holding the arm and its payload against gravity, on the station's own plant
    (the simulated driver's model is exact; a real driver's is not: docs/hardware.md)."""
    plant = arm.plant
    context = plant.CreateDefaultContext()

    def gravity(q: np.ndarray) -> np.ndarray:
        plant.SetPositions(context, arm.instance, q)
        return -plant.GetVelocitiesFromArray(arm.instance, plant.CalcGravityGeneralizedForces(context))

    return gravity
