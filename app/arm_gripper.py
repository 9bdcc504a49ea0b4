"""`safesysid arm-sim`'s gripper and its placement referee (docs/hardware.md).

On an "open" command (drake.lcmt_schunk_wsg_command, arm.gripper_command_channel) the payload is
released where it is (RealArm.release, as the simulated-clock task phase does) unless the arm's
driver refuses (`release_refusal`): a braked arm (watchdog, hold request) or one never commanded
drops nothing, nor, with the controller beside the arm, one not at rest at the end of the task
trajectory (systems/hardware/plan_follower.py); the refusal is an event. The gripper's status
(lcmt_schunk_wsg_status) goes out between the arm's chunks, stamped with the arm's clock. The
referee measures the released payload's centre task.settle_time_s after the release (or at
release, for a place_xyz_m target) against the task's target: the criterion of
app/task_run.py's placement.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pydrake.lcm import DrakeLcm
    from pydrake.systems.framework import Context
    from safesysid.systems.config import Scenario
    from safesysid.systems.hardware.lcm_systems import ArmDriver
    from safesysid.systems.plant.arm_plant import RealArm


class ArmGripper:
    def __init__(self, scenario: Scenario, arm: RealArm, driver: ArmDriver, *, lcm: DrakeLcm) -> None:
        from safesysid.systems.hardware.gripper import GripperServer
        from safesysid.systems.task.phase import placement_target

        cfg = scenario.arm
        self.arm, self.driver, self.scenario = arm, driver, scenario
        self.server = GripperServer(lcm, cfg.gripper_command_channel, cfg.gripper_status_channel)
        self.target, self.kind = placement_target(scenario, arm.dumbbell)
        self.t_release: float | None = None
        self.release_xyz: np.ndarray | None = None
        self.measured: tuple[float, np.ndarray] | None = None  # (arm time, payload centre)
        self.events: list[dict] = []
        self.refusals: set[str] = set()

    def step(self, ctx: Context) -> None:
        """Between the arm's chunks: act on an open command, measure a settled payload, report."""
        t = ctx.get_time()
        if self.t_release is None and self.server.open_requested():
            self._open(ctx, t)
        if self.t_release is not None and self.measured is None and t >= self._measure_at():
            self.measured = (t, self._centre(ctx))
        self.server.publish(t)

    def _open(self, ctx: Context, t: float) -> None:
        driver_ctx = self.driver.GetMyContextFromRoot(ctx)
        why = self.driver.release_refusal(driver_ctx)
        if why is None and self.arm.released_body is None:
            why = "nothing to release"
        if why is not None:
            if why not in self.refusals:  # once per reason: the run repeats its request
                self.refusals.add(why)
                self.events.append(dict(t=t, kind="release_refused", detail=f"open requested while {why}"))
            return
        self.release_xyz = self.arm.release(ctx).translation()
        self.driver.payload_released(self.driver.GetMyMutableContextFromRoot(ctx))
        self.t_release, self.server.is_open = t, True
        where = np.round(self.release_xyz, 4).tolist()
        self.events.append(dict(t=t, kind="release", detail=f"gripper opened: payload released at {where} m"))

    def _measure_at(self) -> float:
        return self.t_release + (0.0 if self.kind == "release" else self.scenario.task.settle_time_s)

    def _centre(self, ctx: Context) -> np.ndarray:
        if self.kind == "release":
            return self.release_xyz
        return self.arm.payload_pose(ctx).translation()

    def judgement(self, ctx: Context, *, safe: bool) -> dict:
        """arm_summary.json's gripper and placement (None without a placement task), and success:
        safe and placed within task.placement_tolerance_m."""
        placement = None
        if self.target is not None:
            at, centre = self.measured or (ctx.get_time(), self._centre(ctx) if self.t_release is not None else None)
            error = None if centre is None else float(np.linalg.norm(centre - self.target))
            placement = {
                "kind": self.kind,
                "released": self.t_release is not None,
                "release_time_s": self.t_release,
                "release_m": None if self.release_xyz is None else self.release_xyz.tolist(),
                "target_m": np.asarray(self.target, float).tolist(),
                "measured_m": None if centre is None else np.asarray(centre, float).tolist(),
                "measured_at_s": at if centre is not None else None,
                "settled_before_the_end": self.measured is not None,
                "error_m": error,
                "tolerance_m": self.scenario.task.placement_tolerance_m,
            }
        placed = placement is None or (  # no placement task: nothing to place
            placement["error_m"] is not None and placement["error_m"] <= placement["tolerance_m"]
        )
        return {
            "gripper": {"open": self.server.is_open, "events": list(self.events)},
            "placement": placement,
            "success": bool(safe and placed),
        }
