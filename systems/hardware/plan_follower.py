"""The controller beside the arm (`arm.control_loop: arm`): the arm side's plan follower.

The run sends each certified plan (plan_message.py) before it starts; the arm's own 1 kHz loop
evaluates the plan at its clock and runs ARMOUR's law on it, so no torque crosses the boundary
(the authors' placement: kinova_robust_control beside the arm, plans from the planner's process).
The follower accepts a plan only when it is
- new (a later start than the last accepted one: the run repeats each plan, LCM is best effort),
- early (received before its start on the arm's clock: Algorithm 2's deadline, here), and
- continuous (it starts at the state the executing trajectory reaches then, exactly: the tube's
  argument needs a continuous desired trajectory);
a plan that is not is refused with an event, and the arm finishes the executing plan, which
brakes to rest (its built-in brake) and holds there: the missed deadline of Algorithm 2. Before
the first plan the arm holds its start pose with the prior parameters, as the run's controller does.

The task phase crosses the same way (its curves are plans, the last one marked `release`). The
gripper may let the payload go only when the arm rests at the end of such a plan
(`release_refusal`: anywhere else the payload would land where nobody planned it), and from the
release on the controller runs with the bare end effector's parameters (`payload_released`): the
arm switches at the instant the payload leaves, which the run only learns from the gripper's status.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, Context, EventStatus, LeafSystem
from safesysid.systems.planner.trajectory_source import at_rest

from .freshness import Freshness
from .lcm_systems import LatestMessage
from .plan_message import Plan, parse_plan

START_TOLERANCE = 1e-9  # the same doubles on both sides (plan_message.py): equal up to rounding


@dataclass(frozen=True)
class Following:
    plans: tuple[Plan, ...] = ()  # accepted, by start time (the executing one and those to come)
    refused: frozenset = frozenset()  # start times refused (their repeats are ignored)
    margins_s: tuple[float, ...] = ()  # per accepted plan: its start minus its arrival [s]
    last_start_s: float | None = None  # the start of the last accepted plan
    released: bool = False  # the payload was let go: the bare end effector's parameters from here
    events: tuple[dict, ...] = ()

    def __deepcopy__(self, memo: dict) -> Following:
        return self  # immutable: Drake copies the state at every step's unrestricted update


class PlanFollower(LeafSystem):
    """Plans (lcmt_drake_signal) -> desired [q, v, a] (3 n) and (θ0, lower, upper) of the plan
    executing at the arm's clock; before any plan, rest at q_start with `prior`; after the payload's
    release, `released` (the bare end effector's (θ0, lower, upper))."""

    def __init__(
        self,
        n: int,
        plans: LatestMessage,
        *,
        time_step_s: float,
        q_start: np.ndarray,
        prior: tuple,
        released: tuple | None = None,
    ) -> None:
        super().__init__()
        self.n, self.plans = n, plans
        self.q_start = np.asarray(q_start, float)
        self.prior = tuple(np.asarray(x, float) for x in prior)
        self.released = None if released is None else tuple(np.asarray(x, float) for x in released)
        self._memo = self.DeclareAbstractState(AbstractValue.Make(Following()))
        self.DeclarePeriodicUnrestrictedUpdateEvent(time_step_s, 0.0, self._tick)
        deps = {self.abstract_state_ticket(self._memo), self.time_ticket()}
        self.DeclareVectorOutputPort("desired", BasicVector(3 * n), self._desired, prerequisites_of_calc=deps)
        for k, name in enumerate(("theta0", "theta_lower", "theta_upper")):
            self.DeclareVectorOutputPort(
                name, len(self.prior[k]), lambda c, out, k=k: out.SetFromVector(self._thetas(c)[k]), deps
            )

    def following(self, context: Context) -> Following:
        return context.get_abstract_state(int(self._memo)).get_value()

    def guard(self, context: Context) -> Freshness:
        """The follower's record in a driver's terms (arm_summary.json's `driver`): armed once a
        plan was accepted; never tripped (a refused plan is an event, and the arm finishes the
        executing one); ignored: the plans refused."""
        st = self.following(context)
        return Freshness(np.inf, last_sent_s=st.last_start_s, ignored=len(st.refused), events=st.events)

    def release_refusal(self, context: Context) -> str | None:
        """Why the gripper must not open now (None: the arm rests at the end of a release plan)."""
        plan = self._executing(self.following(context).plans, context.get_time())
        if plan is None or not plan.release:
            return "the arm is not on the task trajectory's last plan"
        if context.get_time() < plan.piece.t_end:
            return "the arm has not reached the end of the task trajectory"
        return None

    def payload_released(self, context: Context) -> None:
        """The gripper let the payload go: the controller gets the bare end effector's parameters."""
        st = self.following(context)
        event = dict(t=context.get_time(), kind="released_parameters", detail="controller: bare end effector")
        new = replace(st, released=True, events=st.events + (event,))
        context.get_mutable_abstract_state(int(self._memo)).set_value(new)

    def _tick(self, context, state):
        st, t = self.following(context), context.get_time()
        self.plans.receive()
        for msg in self.plans.drain():
            st = self._offer(st, parse_plan(msg, self.n), t)
        st = replace(st, plans=self._from_executing(st.plans, t))
        state.get_mutable_abstract_state(int(self._memo)).set_value(st)
        return EventStatus.Succeeded()

    def _offer(self, st: Following, plan: Plan | None, t: float) -> Following:
        """st with `plan` accepted or refused at t (its repeats and older plans: unchanged)."""
        if plan is None:
            return self._refuse(st, t, None, "plan_malformed", "a plan message of another size or with bad values")
        start = plan.piece.t_start
        if start in st.refused or (st.plans and start <= st.plans[-1].piece.t_start):
            return st
        if start <= t:
            return self._refuse(st, t, start, "plan_late", f"the plan starting at {start:.3f} s arrived at {t:.3f} s")
        expected = self._evaluate(st.plans, start)
        if not all(
            np.allclose(a, b, rtol=0, atol=START_TOLERANCE) for a, b in zip(plan.piece.evaluate(start), expected)
        ):
            detail = f"the plan starting at {start:.3f} s does not start where the executing trajectory is then"
            return self._refuse(st, t, start, "plan_discontinuous", detail)
        return replace(st, plans=st.plans + (plan,), margins_s=st.margins_s + (start - t,), last_start_s=start)

    @staticmethod
    def _refuse(st: Following, t: float, start, kind: str, detail: str) -> Following:
        refused = st.refused if start is None else st.refused | {start}
        return replace(st, refused=refused, events=st.events + (dict(t=t, kind=kind, detail=detail),))

    @staticmethod
    def _from_executing(plans: tuple[Plan, ...], t: float) -> tuple[Plan, ...]:
        """The plans from the one executing at t on (the ones before it are over)."""
        started = [k for k, p in enumerate(plans) if p.piece.t_start <= t]
        return plans[started[-1] :] if started else plans

    @staticmethod
    def _executing(plans: tuple[Plan, ...], t: float) -> Plan | None:
        started = [p for p in plans if p.piece.t_start <= t]
        return started[-1] if started else None

    def _evaluate(self, plans: tuple[Plan, ...], t: float):
        """(q, v, a) at t: the executing plan's (at rest at its end), or the start pose before any."""
        plan = self._executing(plans, t)
        return at_rest(self.q_start) if plan is None else plan.piece.evaluate(t)

    def _desired(self, context, output):
        output.SetFromVector(np.concatenate(self._evaluate(self.following(context).plans, context.get_time())))

    def _thetas(self, context):
        st = self.following(context)
        if st.released and self.released is not None:
            return self.released
        plan = self._executing(st.plans, context.get_time())
        return self.prior if plan is None else plan.thetas
