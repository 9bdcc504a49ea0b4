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

from .lcm_systems import ArmDriver, CommandEncoder, LatestMessage, StatusEncoder, StatusReceiver
from .queued_lcm import QueuedLcm

if TYPE_CHECKING:
    from pydrake.lcm import DrakeLcm
    from pydrake.systems.framework import Context, DiagramBuilder, InputPort, OutputPort
    from safesysid.systems.model.payload import Dumbbell
    from safesysid.systems.model.robot_model import RobotModel
    from safesysid.systems.plant.arm_plant import RealArm

    from ..config import Scenario

# The run waits this long at initialization for the arm's first status (an arm must be answering).
FIRST_STATUS_TIMEOUT_S = 10.0


def make_lcm(scenario: Scenario) -> DrakeLcm:
    from pydrake.lcm import DrakeLcm

    return DrakeLcm(scenario.arm.lcm_url)


def _interface(builder, lcm):
    from pydrake.systems.lcm import LcmInterfaceSystem

    interface = builder.AddSystem(LcmInterfaceSystem(lcm))
    interface.set_name("lcm_interface")
    return interface


@dataclass
class LcmArm:
    """The run's view of an arm reached over LCM: RealArm's ports, without the plant (the
    referee, the ground truth and the payload's release live on the arm's side)."""

    robot: RobotModel
    dumbbell: Dumbbell | None  # the scenario's payload: what the planner assumes it carries
    commanded_torque_input: InputPort
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

    def fault_events(self, context: Context) -> list[dict]:
        return list(self.receiver.guard(self.receiver.GetMyContextFromRoot(context)).events)


def add_lcm_arm(builder: DiagramBuilder, scenario: Scenario, robot: RobotModel, *, lcm: DrakeLcm) -> LcmArm:
    from pydrake.systems.lcm import LcmPublisherSystem
    from safesysid.systems.plant.arm_plant import scenario_dumbbell

    n, h, cfg = robot.n, scenario.plant.time_step_s, scenario.arm
    _interface(builder, lcm)
    # Every status, not one per step (queued_lcm.py); the receiver hands them over at its step.
    statuses = LatestMessage(QueuedLcm(cfg.lcm_url), cfg.status_channel, lcmt_panda_status, backlog=4 * PACKET_ROWS)
    receiver = builder.AddSystem(
        StatusReceiver(
            n, statuses, h, status_timeout_s=cfg.status_timeout_ms * 1e-3, q_start=np.asarray(scenario.q0_rad)
        )
    )
    receiver.set_name("status_receiver")
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
    return LcmArm(
        robot=robot,
        dumbbell=scenario_dumbbell(scenario),
        commanded_torque_input=encoder.torque,
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


def add_arm_driver(builder: DiagramBuilder, arm: RealArm, scenario: Scenario, *, lcm: DrakeLcm) -> ArmDriver:
    """Commands -> ArmDriver (watchdog, hold) -> the station's commanded_torque; its status out
    every plant step. Returns the driver (its torque output is u before saturation: the referee's)."""
    from pydrake.systems.lcm import LcmPublisherSystem

    cfg, h = scenario.arm, scenario.plant.time_step_s
    _interface(builder, lcm)
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
    encoder = builder.AddSystem(StatusEncoder(arm.robot.n))
    encoder.set_name("status_encoder")
    builder.Connect(arm.state_output, encoder.state)
    builder.Connect(arm.measured_torque_output, encoder.measured_torque)
    builder.Connect(driver.get_output_port(), encoder.commanded_torque)
    pub = builder.AddSystem(LcmPublisherSystem.Make(cfg.status_channel, lcmt_panda_status, lcm, publish_period=h))
    pub.set_name("status_publisher")
    builder.Connect(encoder.get_output_port(), pub.get_input_port())
    return driver


def plant_gravity(arm: RealArm) -> Callable[[np.ndarray], np.ndarray]:
    """q -> the torque holding the arm and its payload against gravity, on the station's own plant
    (the simulated driver's model is exact; a real driver's is not: docs/hardware.md)."""
    plant = arm.plant
    context = plant.CreateDefaultContext()

    def gravity(q: np.ndarray) -> np.ndarray:
        plant.SetPositions(context, arm.instance, q)
        return -plant.GetVelocitiesFromArray(arm.instance, plant.CalcGravityGeneralizedForces(context))

    return gravity
