"""The controller beside the arm (`arm.control_loop: arm`): the run side's plan sender.

Each certified plan goes to the arm (plan_message.py on arm.plan_channel) as soon as it exists:
the first one, planned from rest before the clock starts, and then each wall-clock planning
call's plan the moment its worker returns it, ahead of its start t_k (the arm refuses a plan that
arrives after its start: plan_follower.py). A call not back by t_k is the run's missed deadline,
as in the other placement, and nothing is sent for it. Each plan is sent again every period
until it starts on the arm's clock (LCM is best effort: a single message was seen lost; the arm
ignores the repeats). With a task (input `task`, the TaskPhaseSource's state), its curves follow
the same way once the worker has made them, certified with the task's parameters, the last one
marked as the release plan (plan_message.py).

The run's clock and the arm's: a plan starting at t on the run's clock starts at t + offset on the
arm's, offset = (the arm's time of the newest status when the run's clock starts) + arm.plan_lead_ms
− (the run's time then), so the first plan, starting at the clock's start, reaches the arm before
it starts. The pending call lives in the planner, not in the context: this system serves one
wall-clock run.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import EventStatus, LeafSystem
from safesysid.systems.planner.system import PlannerState
from safesysid.systems.planner.trajectory_source import PhaseState, Piece, TimedCurve

from .plan_message import Plan, plan_message

if TYPE_CHECKING:
    from pydrake.lcm import DrakeLcm

    from .background import WallClockPlanner

SEND_PERIOD_S = 0.01  # each plan again every 10 ms until it starts


class PlanSender(LeafSystem):
    """Inputs `plan`: the planner's state (its executing plan), `task` (optional): the task phase's
    state; publishes the plans to come."""

    def __init__(self, planner: WallClockPlanner, lcm: DrakeLcm, channel: str, *, lead_s: float) -> None:
        super().__init__()
        self.planner, self.lcm, self.channel, self.lead_s = planner, lcm, channel, lead_s
        self.offset_s: float | None = None  # arm clock - run clock (start_clock); None: not started
        self.sent: dict[float, bytes] = {}  # run-clock start -> the encoded plan
        self.DeclareAbstractInputPort("plan", AbstractValue.Make(PlannerState()))
        self.task = self.DeclareAbstractInputPort("task", AbstractValue.Make(PhaseState()))
        self.DeclarePeriodicPublishEvent(SEND_PERIOD_S, 0.0, self._send)

    def start_clock(self, arm_time_s: float, run_time_s: float) -> None:
        """The run's clock starts at run_time_s, when the arm's newest status is of arm_time_s."""
        self.offset_s = arm_time_s + self.lead_s - run_time_s

    def _send(self, context) -> EventStatus:
        if self.offset_s is None:
            return EventStatus.DidNothing()
        t = context.get_time()
        st = self.get_input_port(0).Eval(context)
        if st.plan is not None:  # the executing plan: the first one is sent from here
            self._add(st.t_start, st.plan, st.thetas, t)
        pending = self.planner.pending
        if pending is not None and pending[0].done() and pending[1] > t:
            self._add_returned(pending, t)
        if self.task.HasValue(context):
            self._add_task(self.task.Eval(context), t)
        for start in [s for s in self.sent if s + self.lead_s < t]:
            del self.sent[start]  # started on the arm's clock: no more repeats
        for data in self.sent.values():
            self.lcm.Publish(self.channel, data)
        return EventStatus.Succeeded()

    def _add_returned(self, pending, t: float) -> None:
        future, t_start, _, thetas = pending
        if t_start in self.sent:
            return
        try:
            (res, _), *_ = future.result()
        except Exception:  # noqa: BLE001 -- a dead worker: the run's planner_error, nothing to send
            return
        if res.ok:
            self._add(t_start, res, thetas, t)

    def _add(self, t_start: float, res, thetas, t: float) -> None:
        if not self._wanted(t_start, t):
            return
        piece = Piece(t_start + self.offset_s, res.trajectory, np.asarray(res.q_end, float))
        self._queue(t_start, Plan(piece, tuple(np.asarray(x, float) for x in thetas)), t)

    def _add_task(self, st: PhaseState, t: float) -> None:
        """The task's curves, once made (the last one: the release plan)."""
        if st.phase != "task" or not st.ready:
            return
        for k, timed in enumerate(st.curves):
            piece = TimedCurve(timed.t_start + self.offset_s, timed.curve)
            self._queue(timed.t_start, Plan(piece, st.thetas, release=k == len(st.curves) - 1), t)

    def _queue(self, t_start: float, plan: Plan, t: float) -> None:
        """Send `plan` (starting at t_start on the run's clock) from now until it starts."""
        if self._wanted(t_start, t):
            self.sent[t_start] = plan_message(plan, sent_s=t).encode()

    def _wanted(self, t_start: float, t: float) -> bool:
        """Not queued yet, nor started on the arm's clock."""
        return t_start not in self.sent and t_start + self.lead_s >= t
