"""The gripper across the boundary: the payload's release as Drake's Schunk WSG lcmtypes
(`drake.lcmt_schunk_wsg_command` / `lcmt_schunk_wsg_status`, the messages Drake's
ManipulationStation and hardware_sim use for a gripper), docs/hardware.md.

The run asks for "open" (target_position_mm >= OPEN_MM) at the end of the task trajectory and
repeats it (LCM is best effort) until a status received after the first request reports the
gripper open; it switches its controller to the bare end effector only then. No such status
within arm.gripper_timeout_ms: the release did not happen (the payload may still be held), and
the run asks the arm to hold. The arm side (`safesysid arm-sim`) releases the payload on an open
command unless its driver holds (a braked arm drops nothing), and reports the finger opening.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from drake import lcmt_schunk_wsg_command, lcmt_schunk_wsg_status

from .lcm_systems import LatestMessage
from .messages import utime_of

if TYPE_CHECKING:
    from pydrake.lcm import DrakeLcm

OPEN_MM = 110.0  # the WSG 50's full opening: "open", release the payload
CLOSED_MM = 0.0  # fingers on the payload's handle (the width is not modelled)
GRIP_FORCE_N = 40.0


def gripper_command(t_s: float, *, open_: bool) -> lcmt_schunk_wsg_command:
    msg = lcmt_schunk_wsg_command()
    msg.utime = utime_of(t_s)
    msg.target_position_mm = OPEN_MM if open_ else CLOSED_MM
    msg.force = GRIP_FORCE_N
    return msg


def gripper_status(t_s: float, *, is_open: bool) -> lcmt_schunk_wsg_status:
    msg = lcmt_schunk_wsg_status()
    msg.utime = utime_of(t_s)
    msg.actual_position_mm = OPEN_MM if is_open else CLOSED_MM
    msg.actual_force = 0.0 if is_open else GRIP_FORCE_N
    msg.actual_speed_mm_per_s = 0.0
    return msg


def asks_open(msg: lcmt_schunk_wsg_command) -> bool:
    return msg.target_position_mm >= OPEN_MM - 1e-6


def reports_open(msg: lcmt_schunk_wsg_status) -> bool:
    return msg.actual_position_mm >= OPEN_MM - 1e-6


def release_verdict(*, confirmed: bool, waited_s: float, timeout_s: float) -> str:
    """ "open" (a status reporting the gripper open arrived after the request), "waiting", or
    "lost" (none within timeout_s of the first request: the run holds the arm)."""
    if confirmed:
        return "open"
    return "lost" if waited_s > timeout_s else "waiting"


class GripperLink:
    """The run's end of the gripper channels: open requests out, the newest status in."""

    def __init__(self, lcm: DrakeLcm, command_channel: str, status_channel: str) -> None:
        self.lcm, self.command_channel = lcm, command_channel
        self.statuses = LatestMessage(lcm, status_channel, lcmt_schunk_wsg_status)

    def request_open(self, t_s: float) -> None:
        self.lcm.Publish(self.command_channel, gripper_command(t_s, open_=True).encode())

    def mark(self) -> int:
        """The statuses received so far (before an open request)."""
        return self.statuses.count

    def confirmed_since(self, mark: int) -> bool:
        """A status received after `mark` reports the gripper open (a stale "open" does not count)."""
        return self.statuses.count > mark and reports_open(self.statuses.message())


@dataclass
class GripperServer:
    """The arm side: open commands in, the gripper's status out (stamped with the arm's clock)."""

    lcm: DrakeLcm
    command_channel: str
    status_channel: str
    commands: LatestMessage = field(init=False)
    is_open: bool = False
    refused: list = field(default_factory=list)  # open commands received while the arm held

    def __post_init__(self) -> None:
        self.commands = LatestMessage(self.lcm, self.command_channel, lcmt_schunk_wsg_command)

    def open_requested(self) -> bool:
        return bool(self.commands.count) and asks_open(self.commands.message())

    def publish(self, t_s: float) -> None:
        self.lcm.Publish(self.status_channel, gripper_status(t_s, is_open=self.is_open).encode())
