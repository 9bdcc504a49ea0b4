"""Drake's Panda lcmtypes as the arm boundary's messages (docs/hardware.md): pure conversions.

Why Panda and not iiwa: lcmt_panda_command has a pure torque mode (control_mode_expected =
kTorque, the torque applied as sent; drake-franka-driver forwards it to libfranka's torque
control with a command expiry), and lcmt_panda_status carries the arm's own time stamp, the
measured and the commanded torque. The iiwa's kTorqueOnly is a torque added on top of the
robot's own gravity compensation and position servo. Drake's PandaCommandReceiver and
PandaStatusReceiver hide utime and control_mode_expected, which the watchdog, the ordering checks
and the brake request need, so these conversions read the messages themselves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from drake import lcmt_panda_command, lcmt_panda_status

TORQUE_MODE = 4  # PandaControlMode.kTorque
HOLD_MODE = 0  # PandaControlMode.kNone: the run asks the driver to brake and hold


def utime_of(t_s: float) -> int:
    return int(round(t_s * 1e6))


def command_message(t_s: float, torque: np.ndarray, hold: bool = False) -> lcmt_panda_command:
    """The full motor torque u [N m] to apply from t_s (sender's clock); hold: request a brake."""
    msg = lcmt_panda_command()
    msg.utime = utime_of(t_s)
    msg.num_joint_position = msg.num_joint_velocity = 0
    msg.joint_position, msg.joint_velocity = [], []
    msg.num_joint_torque = len(torque)
    msg.joint_torque = [float(x) for x in torque]
    msg.control_mode_expected = HOLD_MODE if hold else TORQUE_MODE
    return msg


@dataclass(frozen=True)
class Status:
    t_s: float  # the arm's own clock
    q: np.ndarray
    v: np.ndarray
    measured_torque: np.ndarray
    commanded_torque: np.ndarray  # what the driver applied (before the actuators' saturation)


def status_message(status: Status) -> lcmt_panda_status:
    n = len(status.q)
    msg = lcmt_panda_status()
    msg.utime = msg.robot_utime = utime_of(status.t_s)
    msg.num_joints = n
    zeros = [0.0] * n
    msg.joint_position = [float(x) for x in status.q]
    msg.joint_velocity = [float(x) for x in status.v]
    msg.joint_torque = [float(x) for x in status.measured_torque]
    msg.joint_torque_desired = [float(x) for x in status.commanded_torque]
    msg.joint_position_desired, msg.joint_velocity_desired = list(msg.joint_position), zeros
    msg.joint_acceleration_desired, msg.joint_torque_external = zeros, zeros
    msg.control_command_success_rate = 1.0
    msg.robot_mode = 0
    msg.control_mode = TORQUE_MODE
    return msg


def parse_status(msg: lcmt_panda_status, n: int) -> Status | None:
    """The status, or None when it is empty or not for n joints (a default, never-received message)."""
    if msg.num_joints != n or len(msg.joint_position) != n:
        return None
    return Status(
        msg.utime * 1e-6,
        np.array(msg.joint_position, float),
        np.array(msg.joint_velocity, float),
        np.array(msg.joint_torque, float),
        np.array(msg.joint_torque_desired, float),
    )


def parse_command(msg: lcmt_panda_command, n: int) -> tuple[float, np.ndarray, bool] | None:
    """(sender time s, torque, hold requested), or None when the message is not an n-joint command."""
    if msg.num_joint_torque != n or len(msg.joint_torque) != n:
        return None
    torque = np.array(msg.joint_torque, float)
    if not np.all(np.isfinite(torque)):
        return None
    return msg.utime * 1e-6, torque, msg.control_mode_expected != TORQUE_MODE
