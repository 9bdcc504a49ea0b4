"""The task phase of `safesysid run --arm lcm` (docs/hardware.md): after identification, the task
trajectory as in the simulated clock (app/task_run.py's TaskPhaseSource, its certificate and its
refusal), the task made in the worker while the loop holds the arm (systems/hardware/
task_source.py), then the payload's release as a gripper "open" over LCM
(systems/hardware/gripper.py) and the settling. The placement is judged by the arm's referee
(`safesysid arm-sim`'s arm_summary.json), which alone sees the payload. With the controller
beside the arm (arm.control_loop arm) the task's curves cross as plans (systems/hardware/
plan_sender.py), the open request waits until they end on the arm's clock (its status), the
run ends once the arm's clock is past the referee's measurement of the settled payload, and the
arm switches its controller to the bare end effector at the release
(systems/hardware/plan_follower.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pydrake.systems.analysis import Simulator
    from safesysid.online_diagram import OnlineDiagram
    from safesysid.systems.config import Scenario

WAIT_CHUNK_S = 0.01  # the run advances this much between looks at the worker and the gripper
ARM_WAIT_S = 30.0  # controller beside the arm: the longest wait for the arm's clock (_wait_for_the_arm)
SETTLED_MARGIN_S = 0.05  # and past the referee's measurement of the settled payload (its 10 ms chunks)


class _Clock:
    """The run's wall-clock advance (online_lcm._pace) over several segments, timing merged."""

    def __init__(self, sim, ctx, pace: Callable) -> None:
        self.sim, self.ctx, self.pace, self.parts = sim, ctx, pace, []

    def now(self) -> float:
        return self.ctx.get_time()

    def to(self, t_s: float) -> None:
        if t_s > self.now() + 1e-9:
            self.parts.append(self.pace(self.sim, self.ctx, t_s))

    def timing(self) -> dict:
        parts = self.parts or [
            {"wall_time_s": 0.0, "max_lag_s": 0.0, "max_lag_at_s": None, "cpu_time_s": 0.0, "loop_cpu_time_s": 0.0}
        ]
        worst = max(parts, key=lambda p: p["max_lag_s"])
        return {
            "wall_time_s": float(sum(p["wall_time_s"] for p in parts)),
            "max_lag_s": float(worst["max_lag_s"]),
            "max_lag_at_s": worst["max_lag_at_s"],
            "cpu_time_s": float(parts[-1]["cpu_time_s"]),
            "loop_cpu_time_s": float(sum(p["loop_cpu_time_s"] for p in parts)),
        }


def run_task_lcm(
    built: OnlineDiagram, sim: Simulator, scenario: Scenario, *, method: str, pace: Callable
) -> tuple[dict, dict]:
    """Advance the wall-clock run through identification, the task, the release and the settling.
    Returns (the task's summary, timing); the task's `hold` is True when the run must stop and
    ask the arm to hold at once (the gripper did not confirm the release)."""
    from safesysid.systems.hardware.gripper import GripperLink
    from safesysid.task_run import task_certificate_summary

    ctx = sim.get_mutable_context()
    clock, source, arm, cfg = _Clock(sim, ctx, pace), built.source, built.arm, scenario.arm
    gripper = GripperLink(arm.lcm, cfg.gripper_command_channel, cfg.gripper_status_channel)
    clock.to(source.switch_time_s + scenario.plant.time_step_s)
    while getattr(source, "pending", None) is not None:  # the worker makes the task; the arm holds
        clock.to(clock.now() + WAIT_CHUNK_S)
    st = source.phase_state(source.GetMyContextFromRoot(ctx))
    certificate = task_certificate_summary(st, None, arm.robot)  # the truth is the arm's
    clock.to(max(st.t_end, clock.now()))
    _wait_for_the_arm(clock, arm, _on_arm_clock(arm, st.t_end))
    t_release, events, hold = clock.now(), [], False
    if st.ready:
        hold, events = _release(built, clock, scenario, gripper=gripper, method=method)
    if not hold:
        clock.to(clock.now() + scenario.task.settle_time_s)
    if st.ready and not hold and arm.plan_sender is not None:  # until the arm's referee measured the payload
        opened_s = gripper.statuses.message().utime * 1e-6  # the arm's clock (app/arm_gripper.py)
        _wait_for_the_arm(clock, arm, opened_s + scenario.task.settle_time_s + SETTLED_MARGIN_S)
    end = clock.now()
    return _summary(built, ctx, scenario, st=st, certificate=certificate, times=(t_release, end), events=events) | {
        "hold": hold
    }, clock.timing()


def _on_arm_clock(arm, run_time_s: float) -> float | None:
    """The arm's time of run_time_s with the controller beside the arm (plan_sender.py's offset:
    the plans' start times there); None when this run's controller drives the arm."""
    return None if arm.plan_sender is None else run_time_s + arm.plan_sender.offset_s


def _wait_for_the_arm(clock: _Clock, arm, arm_time_s: float | None) -> None:
    """Advance until the arm's newest status is of arm_time_s on its own clock, at most
    ARM_WAIT_S. The arm's clock is the one that counts with the controller beside the arm (the
    gripper opens only at rest at the task's end, the referee measures the settled payload on
    it); a simulated arm falls behind real time when starved of CPU (seconds, measured under a
    loaded test suite), a real one does not. arm_time_s None: nothing to wait for."""
    from safesysid.systems.hardware.messages import parse_status

    deadline = clock.now() + ARM_WAIT_S
    while arm_time_s is not None and clock.now() < deadline:
        status = parse_status(arm.statuses.message(), arm.robot.n)
        if status is not None and status.t_s >= arm_time_s:
            return
        clock.to(clock.now() + WAIT_CHUNK_S)


def _release(built, clock: _Clock, scenario: Scenario, *, gripper, method: str) -> tuple[bool, list[dict]]:
    """Ask the gripper to open (again every WAIT_CHUNK_S: LCM is best effort) until a new status
    reports it open, then the controller gets the bare end effector. (hold, events)."""
    from safesysid.systems.hardware.gripper import release_verdict
    from safesysid.task_run import switch_to_released

    timeout_s = scenario.arm.gripper_timeout_ms * 1e-3
    mark, t_ask = gripper.mark(), clock.now()
    verdict = "waiting"
    while verdict == "waiting":
        gripper.request_open(clock.now())
        clock.to(clock.now() + WAIT_CHUNK_S)
        verdict = release_verdict(
            confirmed=gripper.confirmed_since(mark), waited_s=clock.now() - t_ask, timeout_s=timeout_s
        )
    if verdict == "open":
        switch_to_released(built, clock.ctx, scenario, method=method, t=clock.now(), where=None)
        detail = f"the gripper reported open {1e3 * (clock.now() - t_ask):.0f} ms after the request"
        return False, [dict(t=clock.now(), kind="gripper_open", detail=detail)]
    detail = (
        f"no open status from {scenario.arm.gripper_status_channel!r} within {timeout_s * 1e3:g} ms "
        "(arm.gripper_timeout_ms) of the release request: the payload may still be held; the arm is asked to hold"
    )
    return True, [dict(t=clock.now(), kind="gripper_lost", detail=detail)]


def _summary(built, ctx, scenario: Scenario, *, st, certificate, times, events) -> dict:
    from safesysid.systems.task.phase import placement_target
    from safesysid.task_run import task_summary

    target, kind = placement_target(scenario, built.arm.dumbbell)
    placement = {
        "kind": kind or None,
        "target_m": None if target is None else np.asarray(target, float).tolist(),
        "error_m": None,  # the arm's referee measures it (arm_summary.json's placement)
        "tolerance_m": scenario.task.placement_tolerance_m,
        "judged_by": "arm",
    }
    summary = task_summary(built, ctx, scenario, st=st, certificate=certificate, times=times, placement=placement)
    summary["events"] = list(summary["events"]) + events
    return summary
