"""ExcitingPlanner: thin Drake LeafSystem around planner.SafePlanner (receding horizon, Alg. 2).

Outputs the desired q, qd, qdd of the current plan. Plans once at initialization from rest at q0,
then every t_p from the state the current plan reaches at that instant (known exactly: it is the
desired trajectory). A failed planning call keeps the current plan, which ends at rest (the
braking manoeuvre), and ends the loop, as Algorithm 2 does. After `num_plans` calls the last
plan simply runs to rest. Inputs theta0, theta_lower, theta_upper (14 n each) come from the
estimator; when unconnected the constructor's values are used.

Certificates: a plan is safe only under the parameters it was verified with, so the planner
keeps them with the plan and outputs them (plan_theta0, plan_theta_lower, plan_theta_upper) for
as long as that plan executes; the controller reads its parameters from these ports, never from
the estimator. It therefore switches exactly at the start of a plan verified with the new
parameters, whatever the estimator publishes meanwhile (Drake runs this unrestricted update
before the estimator's discrete update at the same t_p, so the plan started at t_p uses the
estimate published at the previous t_p, as in Algorithm 2, where line 7 plans before line 8
identifies).

Input estimate_consistent (1.0 / 0.0; 1.0 when unconnected): at a planning instant where it
reads 0 the planner does not plan again (the identified box is no longer trusted); the robot
finishes, and so brakes on, its verified plan. Events (plan_failed, plan_refused, brake) are kept
as {t, kind, detail} in the state for summary.json.

Everything a run accumulates (the plans, their records and results, the random generator) is in
the abstract state PlannerState, so two contexts of one diagram never share it.
"""

from __future__ import annotations

import copy
import dataclasses
import time

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import EventStatus, LeafSystem

from .trajectory_source import at_rest


@dataclasses.dataclass
class PlannerState:
    plan: object = None  # PlanResult being followed (None: hold q0)
    t_start: float = 0.0  # simulation time at which `plan` started
    calls: int = 0  # planning calls made
    done: bool = False  # no more planning (num_plans reached, a call failed or was refused)
    records: tuple = ()  # one dict per planning call
    results: tuple = ()  # the PlanResult of every planning call (failed ones too)
    rng: object = None  # numpy Generator of the random plans and starts; advanced by each call
    thetas: tuple = ()  # (theta0, lower, upper) `plan` was certified with (before any plan: the last call's)
    events: tuple = ()  # {t, kind, detail}: plan_failed, plan_refused, brake


class ExcitingPlanner(LeafSystem):
    def __init__(
        self, planner, q0, theta0, theta_lower, theta_upper, num_plans=None, replan_period_s=None, mode=None, seed=0
    ):
        super().__init__()
        self._planner = planner
        cfg = planner.config
        n = planner.robot.n
        self._q0 = np.asarray(q0, float).copy()
        self._defaults = [np.asarray(x, float).copy() for x in (theta0, theta_lower, theta_upper)]
        self._num_plans = int(cfg.num_plans if num_plans is None else num_plans)
        self._period = float(cfg.replan_period_s if replan_period_s is None else replan_period_s)
        self._mode = mode
        self._seed = seed
        p = 14 * n
        self._theta0 = self.DeclareVectorInputPort("theta0", p)
        self._theta_lo = self.DeclareVectorInputPort("theta_lower", p)
        self._theta_hi = self.DeclareVectorInputPort("theta_upper", p)
        self._consistent = self.DeclareVectorInputPort("estimate_consistent", 1)
        self._state = self.DeclareAbstractState(AbstractValue.Make(PlannerState(thetas=tuple(self._defaults))))
        deps = {self.abstract_state_ticket(self._state), self.time_ticket()}
        for k, name in enumerate(("q_desired", "v_desired", "a_desired")):
            self.DeclareVectorOutputPort(
                name, n, lambda c, out, k=k: out.SetFromVector(self._desired(c)[k]), prerequisites_of_calc=deps
            )
        for k, name in enumerate(("plan_theta0", "plan_theta_lower", "plan_theta_upper")):
            self.DeclareVectorOutputPort(
                name,
                p,
                lambda c, out, k=k: out.SetFromVector(self._get(c).thetas[k]),
                prerequisites_of_calc={self.abstract_state_ticket(self._state)},
            )
        self.DeclareAbstractOutputPort(
            "plan",
            lambda: AbstractValue.Make(PlannerState()),
            lambda c, out: out.set_value(self._get(c)),
            prerequisites_of_calc=deps,
        )
        self.DeclareInitializationUnrestrictedUpdateEvent(self._on_init)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self._period, self._period, self._on_period)

    # -- helpers ---------------------------------------------------------------------------------
    def _get(self, context) -> PlannerState:
        return context.get_abstract_state(int(self._state)).get_value()

    def planner_state(self, context) -> PlannerState:
        return self._get(context)

    def records(self, context):
        return list(self._get(context).records)

    def events(self, context):
        return list(self._get(context).events)

    def results(self, context):
        """Every planning call's PlanResult, in order (failed ones too)."""
        return list(self._get(context).results)

    def _desired_at(self, st: PlannerState, t):
        if st.plan is None:
            return at_rest(self._q0)
        q, v, a = st.plan.evaluate([t - st.t_start])
        return q[0], v[0], a[0]

    def _desired(self, context):
        return self._desired_at(self._get(context), context.get_time())

    def _thetas(self, context):
        out = []
        for port, default in zip((self._theta0, self._theta_lo, self._theta_hi), self._defaults):
            out.append(port.Eval(context) if port.HasValue(context) else default)
        return out

    def _estimate_consistent(self, context):
        return not self._consistent.HasValue(context) or self._consistent.Eval(context)[0] > 0.5

    # -- events ----------------------------------------------------------------------------------
    def _on_init(self, context, state):
        self._plan_into(
            context, state, PlannerState(thetas=tuple(self._defaults), rng=np.random.default_rng(self._seed))
        )
        return EventStatus.Succeeded()

    def _on_period(self, context, state):
        st = self._get(context)
        if not st.done:
            self._plan_into(context, state, st)
        return EventStatus.Succeeded()

    def _plan_into(self, context, state, st: PlannerState):
        t = context.get_time()
        if not self._estimate_consistent(context):
            new = dataclasses.replace(
                st,
                done=True,
                events=st.events
                + self._stop_events(st, t, "plan_refused", "the estimate is inconsistent: no further plans"),
            )
            state.get_mutable_abstract_state(int(self._state)).set_value(new)
            return
        q, v, a = self._desired_at(st, t)
        thetas = tuple(np.array(x, float) for x in self._thetas(context))
        k_prev = None if st.plan is None else st.plan.k
        rng = copy.deepcopy(st.rng)  # the stored one may be shared with other copies of this state
        wall = time.perf_counter()
        res = self._planner.plan(q, v, a, *thetas, k_init=k_prev, rng=rng, mode=self._mode)
        wall = time.perf_counter() - wall
        calls = st.calls + 1
        record = dict(
            t_s=t,
            index=calls - 1,
            ok=res.ok,
            status=res.status,
            reason=res.reason,
            cost=res.cost,
            cond=res.cond,
            solve_time_s=res.solve_time_s,
            wall_s=wall,
            solver=res.solver,
            solver_status=res.solver_status,
            braking=not res.ok and st.plan is not None,
            k=None if res.k is None else res.k.tolist(),
            min_clearance_m=res.min_clearance_m,
            max_torque_ratio=res.max_torque_ratio,
            constraints=res.num_collision_constraints,
        )
        new = dataclasses.replace(st, calls=calls, records=st.records + (record,), results=st.results + (res,), rng=rng)
        if res.ok:
            new.plan, new.t_start, new.thetas = res, t, thetas
        else:
            new.events = st.events + self._stop_events(st, t, "plan_failed", f"{res.status}: {res.reason}")
            if st.plan is None:
                new.thetas = thetas  # holding q0: the parameters of the latest call
        new.done = (not res.ok) or calls >= self._num_plans
        state.get_mutable_abstract_state(int(self._state)).set_value(new)

    def _stop_events(self, st: PlannerState, t, kind, detail):
        """The event that ends planning, and the brake it implies when a plan is executing."""
        events = (dict(t=t, kind=kind, detail=detail),)
        if st.plan is not None:
            end = st.t_start + st.plan.trajectory.duration
            events += (
                dict(
                    t=t,
                    kind="brake",
                    detail=f"finishing the verified plan started at {st.t_start:.3f} s (at rest at {end:.3f} s)",
                ),
            )
        return events
