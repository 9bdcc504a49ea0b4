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
parameters, whatever the estimator publishes meanwhile (this update and the estimator's at the
same t_p are both unrestricted and read the context before either applies, so the plan started
at t_p uses the estimate published at the previous t_p, as in Algorithm 2, where line 7 plans
before line 8 identifies).

Input estimate_consistent (1.0 / 0.0; 1.0 when unconnected): at a planning instant where it
reads 0 the planner does not plan again (the identified box is no longer trusted); the robot
finishes, and so brakes on, its verified plan. Events (plan_failed, plan_refused, brake) are kept
as {t, kind, detail} in the state for summary.json.

Injected faults (scenario `faults`, systems/plant/faults.py): `forced_failures` {call index: status}
makes those planning calls fail as a solver failure or timeout would (no verified plan: the robot
brakes on the executing one). `appearing` [(t_s, Obstacle)]: at t_s the obstacle joins the
planner's world (every later plan is certified against it), and the executing plan, certified
without it, is checked against it on its certified swept spheres: if they still clear it the
plan keeps its certificate; if not, it is invalidated: no further plans, and the robot brakes on
it, which is then NOT certified against the new obstacle (events obstacle_appeared,
plan_invalidated, brake say so).

Everything a run accumulates (the plans, their records and results, the random generator) is in
the abstract state PlannerState, so two contexts of one diagram never share it.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import time
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import EventStatus, LeafSystem
from safesysid.systems.planner.safe_planner import PlanResult
from safesysid.systems.planner.trajectory_source import Piece, at_rest
from safesysid.systems.planner.world import remaining_plan_clearance, with_obstacle

if TYPE_CHECKING:
    from pydrake.systems.framework import Context
    from safesysid.systems.config import Obstacle
    from safesysid.systems.planner.safe_planner import SafePlanner


@dataclasses.dataclass
class PlannerState:
    plan: PlanResult | None = None  # PlanResult being followed (None: hold q0)
    t_start: float = 0.0  # simulation time at which `plan` started
    calls: int = 0  # planning calls made
    done: bool = False  # no more planning (num_plans reached, a call failed or was refused)
    records: tuple[dict, ...] = ()  # one dict per planning call
    results: tuple[PlanResult, ...] = ()  # the PlanResult of every planning call (failed ones too)
    rng: np.random.Generator | None = None  # of the random plans and starts; advanced by each call
    thetas: tuple = ()  # (theta0, lower, upper) `plan` was certified with (before any plan: the constructor's)
    events: tuple[dict, ...] = ()  # {t, kind, detail}: plan_failed, plan_refused, brake
    past: np.ndarray | None = None  # W_e rows of the executed plans (planner.cumulative_excitation)

    @functools.cached_property
    def piece(self) -> Piece | None:
        """`plan` as a trajectory piece (monomial coefficients: the desired state is read every
        control step, so it is computed once per plan, not per evaluation)."""
        return None if self.plan is None else Piece(self.t_start, self.plan.trajectory, self.plan.q_end)


class ExcitingPlanner(LeafSystem):
    def __init__(
        self,
        planner: SafePlanner,
        q0: ArrayLike,
        theta0: ArrayLike,
        theta_lower: ArrayLike,
        theta_upper: ArrayLike,
        *,
        num_plans: int | None = None,
        replan_period_s: float | None = None,
        mode: str | None = None,
        seed: int = 0,
        forced_failures: Mapping[int, str] | None = None,
        appearing: Iterable[tuple[float, Obstacle]] = (),
    ) -> None:
        super().__init__()
        self._planner = planner
        self._forced = dict(forced_failures or {})
        # (t_s, the obstacle, the planner of the world from t_s on), in time order.
        self._worlds = []
        for t_s, obstacle in sorted(appearing, key=lambda a: a[0]):
            before = self._worlds[-1][2] if self._worlds else planner
            self._worlds.append((float(t_s), obstacle, with_obstacle(before, obstacle)))
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
        for index, (t_s, _, _) in enumerate(self._worlds):
            # One-shot: Drake has no timed one-shot event; a period longer than any run.
            self.DeclarePeriodicUnrestrictedUpdateEvent(
                1e9, t_s, lambda c, s, index=index: self._on_obstacle(c, s, index)
            )

    # -- helpers ---------------------------------------------------------------------------------
    def _get(self, context) -> PlannerState:
        return context.get_abstract_state(int(self._state)).get_value()

    def planner_state(self, context: Context) -> PlannerState:
        return self._get(context)

    def records(self, context: Context) -> list[dict]:
        return list(self._get(context).records)

    def events(self, context: Context) -> list[dict]:
        return list(self._get(context).events)

    def results(self, context: Context) -> list[PlanResult]:
        """Every planning call's PlanResult, in order (failed ones too)."""
        return list(self._get(context).results)

    def _desired_at(self, st: PlannerState, t):
        if st.piece is None:
            return at_rest(self._q0)
        return st.piece.evaluate(t)

    def _desired(self, context):
        # q, v and a are three output ports, each evaluated at every 1 kHz step: the piece is
        # evaluated once per (piece, t) for the three (a pure function of both).
        st, t = self._get(context), context.get_time()
        memo = getattr(self, "_desired_memo", None)
        if memo is None or memo[0] is not st.piece or memo[1] != t:
            memo = self._desired_memo = (st.piece, t, self._desired_at(st, t))
        return memo[2]

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

    def _planner_at(self, t):
        """The planner of the world at t (every obstacle appeared by then)."""
        known = [p for t_s, _, p in self._worlds if t_s <= t]
        return known[-1] if known else self._planner

    def _on_obstacle(self, context, state, index):
        st, t = self._get(context), context.get_time()
        _, obstacle, _ = self._worlds[index]
        appeared = dict(t=t, kind="obstacle_appeared", detail=f"obstacle {obstacle.name!r}: every later plan avoids it")
        if st.plan is None:
            events = (appeared,)
        else:
            margin, first = remaining_plan_clearance(st.plan, t - st.t_start, [obstacle])
            if margin >= 0:
                appeared["detail"] += f"; the executing plan's certified spheres clear it by {margin:.4f} m"
                events = (appeared,)
            else:
                detail = (
                    f"the executing plan (started at {st.t_start:.3f} s, certified without {obstacle.name!r}) reaches "
                    f"{-margin:.4f} m into it on its certified spheres from {st.t_start + first:.3f} s"
                )
                note = f"; NOT certified against {obstacle.name!r}"
                events = (appeared,) + self._stop_events(st, t, "plan_invalidated", detail, note)
                st = dataclasses.replace(st, done=True)
        state.get_mutable_abstract_state(int(self._state)).set_value(dataclasses.replace(st, events=st.events + events))
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
        forced = self._forced.get(st.calls)
        past = st.past
        if st.plan is not None and self._planner.config.cumulative_excitation:
            executed = self._planner.executed_rows(st.plan, t - st.t_start, thetas[0])
            past = executed if past is None else np.vstack([past, executed])
        if forced is None:
            try:
                res = self._planner_at(t).plan(q, v, a, *thetas, k_init=k_prev, rng=rng, mode=self._mode, past=past)
            except Exception as err:  # noqa: BLE001 -- any failure of a call is that call's: brake, logged
                reason = f"{type(err).__name__}: {err}"
                res = PlanResult(ok=False, status="planner_error", reason=reason, solver=self._planner.config.solver)
        else:  # injected: the solver failed or did not return in time, no verified plan
            res = PlanResult(ok=False, status=forced, reason="injected fault", solver=self._planner.config.solver)
            st = dataclasses.replace(
                st, events=st.events + (dict(t=t, kind="fault_planner", detail=f"planning call {st.calls}: {forced}"),)
            )
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
            refined=bool(res.details.get("refined", False)),  # planner.point_refinement adopted a point
        )
        new = dataclasses.replace(
            st, calls=calls, records=st.records + (record,), results=st.results + (res,), rng=rng, past=past
        )
        if res.ok:  # it executes with the parameters it was certified with (guarantee 6)
            new.plan, new.t_start, new.thetas = res, t, thetas if res.thetas is None else res.thetas
        else:
            # The parameters stay those of the executing plan (before any plan: the constructor's, the
            # prior the hold at q0 was set up with): no plan certified the ones this call was asked with.
            new.events = st.events + self._stop_events(st, t, "plan_failed", f"{res.status}: {res.reason}")
        new.done = (not res.ok) or calls >= self._num_plans
        state.get_mutable_abstract_state(int(self._state)).set_value(new)

    def _stop_events(self, st: PlannerState, t, kind, detail, note=""):
        """The event that ends planning, and the brake it implies when a plan is executing."""
        events = (dict(t=t, kind=kind, detail=detail),)
        if st.plan is not None:
            end = st.t_start + st.plan.trajectory.duration
            events += (
                dict(
                    t=t,
                    kind="brake",
                    detail=f"finishing the verified plan started at {st.t_start:.3f} s (at rest at {end:.3f} s){note}",
                ),
            )
        return events
