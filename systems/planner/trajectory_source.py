"""Desired trajectory sources: [q_d, qd_d, qdd_d] (3 n) from degree-5 Bezier pieces; TaskPhaseSource
(below) switches a run from the planner's plans to the task phase.

A piece is (t_start_s, QuinticBezier, q_end). At time t the latest piece with t_start <= t is
evaluated at t - t_start (after its duration it rests at q_end: the built-in brake). Pieces
live in the context (abstract state), so a planner can append pieces while the diagram runs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, Context, EventStatus, LeafSystem
from safesysid.systems.math.bezier import DEGREE, QuinticBezier, _monomial_of_bernstein

if TYPE_CHECKING:
    from safesysid.systems.math.piecewise_bezier import PiecewiseBezier

_POWERS = np.arange(DEGREE + 1)


def at_rest(q: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, qd, qdd) holding still at q (fresh arrays)."""
    q = np.array(q, float)
    return q, np.zeros_like(q), np.zeros_like(q)


@dataclass(frozen=True)
class Piece:
    t_start: float
    curve: QuinticBezier
    q_end: np.ndarray

    def __post_init__(self):
        # Monomial coefficients in s = (t - t_start)/T, so one evaluation is three small dot
        # products (the source runs every control step); equal to QuinticBezier.evaluate.
        coef = _monomial_of_bernstein(DEGREE) @ self.curve.control_points(self.q_end)
        T = self.curve.duration
        object.__setattr__(self, "_c0", coef)
        object.__setattr__(self, "_c1", coef[1:] * _POWERS[1:, None] / T)
        object.__setattr__(self, "_c2", coef[2:] * (_POWERS[2:] * (_POWERS[2:] - 1))[:, None] / T**2)

    def evaluate(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, qd, qdd) at absolute time t; at rest at q_end after the duration."""
        s = (t - self.t_start) / self.curve.duration
        if s >= 1.0:
            return at_rest(np.broadcast_to(np.asarray(self.q_end, float), self._c0.shape[1:]))
        pw = max(s, 0.0) ** _POWERS
        return pw @ self._c0, pw[:-1] @ self._c1, pw[:-2] @ self._c2


def evaluate_pieces(pieces: list[Piece], t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, qd, qdd) of a sorted piece list at time t (before the first piece: its start, at rest)."""
    if not pieces:
        raise ValueError("trajectory has no pieces")
    active = pieces[0]
    for piece in pieces:
        if piece.t_start <= t + 1e-12:
            active = piece
        else:
            break
    if t < active.t_start:
        return at_rest(active.curve.q0)
    return active.evaluate(t)


def _is_single_curve(trajectory):
    """True for one (QuinticBezier, q_end) from t = 0 (the other form: a list of Piece)."""
    return isinstance(trajectory, tuple) and len(trajectory) == 2 and isinstance(trajectory[0], QuinticBezier)


def _as_pieces(trajectory):
    if isinstance(trajectory, QuinticBezier):
        raise TypeError("pass (QuinticBezier, q_end) or a list of Piece")
    if _is_single_curve(trajectory):
        return [Piece(0.0, trajectory[0], np.asarray(trajectory[1], float))]
    pieces = list(trajectory)
    return sorted(pieces, key=lambda p: p.t_start)


class TrajectorySource(LeafSystem):
    """Output 'desired' (3 n): (q, qd, qdd) of its pieces at the context's time; the pieces are
    abstract state, so a planner replaces them per context (set_pieces, append_piece)."""

    def __init__(self, n: int, trajectory: tuple[QuinticBezier, np.ndarray] | list[Piece]) -> None:
        super().__init__()
        self._pieces_index = self.DeclareAbstractState(AbstractValue.Make(_as_pieces(trajectory)))
        self.DeclareVectorOutputPort(
            "desired",
            BasicVector(3 * n),
            self._calc,
            prerequisites_of_calc={self.time_ticket(), self.abstract_state_ticket(self._pieces_index)},
        )

    def pieces(self, context: Context) -> list[Piece]:
        return context.get_abstract_state(self._pieces_index).get_value()

    def set_pieces(self, context: Context, pieces: tuple[QuinticBezier, np.ndarray] | list[Piece]) -> None:
        """Replace the pieces (context: this system's context)."""
        context.get_mutable_abstract_state(self._pieces_index).set_value(_as_pieces(pieces))

    def append_piece(self, context: Context, piece: Piece) -> None:
        self.set_pieces(context, list(self.pieces(context)) + [piece])

    def _calc(self, context: Context, output: BasicVector) -> None:
        q, qd, qdd = evaluate_pieces(self.pieces(context), context.get_time())
        output.SetFromVector(np.concatenate([q, qd, qdd]))


def make_trajectory_source(n: int, trajectory: tuple[QuinticBezier, np.ndarray] | list[Piece]) -> LeafSystem:
    """A source of [q_d, qd_d, qdd_d] (3 n) on its output port 0. One fixed (QuinticBezier, q_end)
    from t = 0 becomes Drake's TrajectorySource over a BezierCurve (evaluated in C++, clamped
    after its end: at rest at q_end, as Piece.evaluate); a list of Piece this module's
    TrajectorySource, whose pieces can change while the diagram runs."""
    if _is_single_curve(trajectory):
        from pydrake.systems.primitives import TrajectorySource as DrakeTrajectorySource
        from pydrake.trajectories import BezierCurve

        curve, q_end = trajectory
        points = curve.control_points(np.asarray(q_end, float)).T  # (n, 6)
        return DrakeTrajectorySource(BezierCurve(0.0, curve.duration, points), output_derivative_order=2)
    return TrajectorySource(n, trajectory)


# ---------------------------------------------------------------------------------------------
# The run's source: the planner's plans during identification, then the task
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TimedCurve:
    """A rest-to-rest curve (task_trajectory.PiecewiseBezier: .duration, .evaluate(t, orders))
    started at t_start (absolute)."""

    t_start: float
    curve: PiecewiseBezier

    @property
    def t_end(self) -> float:
        return self.t_start + self.curve.duration

    def evaluate(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, qd, qdd) at absolute time t (at rest at its ends outside the curve)."""
        return self.curve.evaluate_at(t - self.t_start)


def evaluate_timed(
    curves: Iterable[TimedCurve], t: float, q_rest: ArrayLike
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, qd, qdd) at time t: the latest curve started by t (at rest at its end afterwards);
    before the first, at rest at q_rest."""
    active = None
    for c in curves:
        if c.t_start <= t + 1e-12:
            active = c
    return at_rest(q_rest) if active is None else active.evaluate(t)


@dataclass(frozen=True)
class PhaseState:
    """TaskPhaseSource's run data (abstract state; immutable, replaced on change)."""

    phase: str = "identification"  # identification | task
    t_switch: float = float("nan")  # when the task phase started
    q_switch: np.ndarray | None = None  # desired q at the switch (at rest)
    curves: tuple = ()  # TimedCurve: the return move (if any) and the task trajectory
    ready: bool = False  # the task's curves were found (False: holding at q_switch)
    thetas: tuple = ()  # (theta0, lower, upper) the controller uses in the task phase
    events: tuple = ()  # {t, kind, detail}
    report: dict = dataclasses.field(default_factory=dict)  # make_task's report (the task's certificate)

    def __deepcopy__(self, memo):
        return self  # immutable: Drake's state copies (every step, for the monitor's update) share it

    @property
    def t_end(self) -> float:
        """End of the last curve (the release instant), or the switch when there is none."""
        return self.curves[-1].t_end if self.curves else self.t_switch


class TaskPhaseSource(LeafSystem):
    """Desired trajectory and controller parameters of a run with a task phase.

    Until `switch_time_s` it passes the planner's desired [q, qd, qdd] (input plan_desired) and
    the parameters the executing plan was certified with (plan_theta0, plan_theta_lower,
    plan_theta_upper) through. At `switch_time_s` (at initialization when it is 0: methods
    without an identification phase) it latches the method's task parameters (inputs
    task_theta0, task_theta_lower, task_theta_upper: the identified box for ours), frozen for the
    whole task whatever those inputs do later, and asks `make_task(q_now, thetas)` for the curves
    from the desired q at that instant, which must be at rest (the last plan's end; q0 when
    plan_desired is unconnected), to be certified with the latched thetas. make_task returns
    (curves [rest-to-rest, played one after the other], events [{kind, detail}], report {});
    no curves: the arm holds.
    Outputs: desired (3n), theta0, theta_lower, theta_upper (p), phase (1: 0 identification,
    1 task), phase_state (PhaseState). `set_thetas` replaces the task parameters (the payload's release).
    """

    def __init__(self, n, num_params, q0, *, switch_time_s, make_task):
        super().__init__()
        from pydrake.common.value import AbstractValue
        from pydrake.systems.framework import BasicVector

        self._n, self._q0, self._make_task = n, np.asarray(q0, float).copy(), make_task
        self.switch_time_s = float(switch_time_s)
        self._plan_desired = self.DeclareVectorInputPort("plan_desired", 3 * n)
        names = ("theta0", "theta_lower", "theta_upper")
        self._plan_thetas = [self.DeclareVectorInputPort(f"plan_{k}", num_params) for k in names]
        self._task_thetas = [self.DeclareVectorInputPort(f"task_{k}", num_params) for k in names]
        self._state = self.DeclareAbstractState(AbstractValue.Make(PhaseState()))
        deps = {self.abstract_state_ticket(self._state), self.time_ticket(), self.all_input_ports_ticket()}
        self.DeclareVectorOutputPort("desired", BasicVector(3 * n), self._calc_desired, prerequisites_of_calc=deps)
        for k, name in enumerate(names):
            self.DeclareVectorOutputPort(
                name,
                BasicVector(num_params),
                lambda c, out, k=k: out.SetFromVector(self._thetas(c)[k]),
                prerequisites_of_calc=deps,
            )
        self.DeclareVectorOutputPort(
            "phase",
            BasicVector(1),
            lambda c, out: out.SetFromVector([float(self.phase_state(c).phase == "task")]),
            prerequisites_of_calc={self.abstract_state_ticket(self._state)},
        )
        self.DeclareAbstractOutputPort(  # the task's curves, for a controller beside the arm (plan_sender.py)
            "phase_state",
            lambda: AbstractValue.Make(PhaseState()),
            lambda c, out: out.set_value(self.phase_state(c)),
            prerequisites_of_calc={self.abstract_state_ticket(self._state)},
        )
        self.DeclareInitializationUnrestrictedUpdateEvent(self._on_init)
        if self.switch_time_s > 0:
            # Fires at the switch (and at its multiples, ignored once in the task phase).
            self.DeclarePeriodicUnrestrictedUpdateEvent(self.switch_time_s, self.switch_time_s, self._on_switch)

    def phase_state(self, context: Context) -> PhaseState:
        return context.get_abstract_state(int(self._state)).get_value()

    def events(self, context: Context) -> list[dict]:
        return list(self.phase_state(context).events)

    def set_thetas(self, context: Context, thetas: Iterable[ArrayLike], event: dict | None = None) -> None:
        """Replace the task parameters (this system's context), logging `event` ({t, kind, detail})."""
        st = self.phase_state(context)
        events = st.events + ((event,) if event else ())
        new = dataclasses.replace(st, thetas=tuple(np.array(x, float) for x in thetas), events=events)
        context.get_mutable_abstract_state(int(self._state)).set_value(new)

    def _thetas(self, context):
        st = self.phase_state(context)
        if st.phase == "task":
            return st.thetas
        return [port.Eval(context) for port in self._plan_thetas]

    def _calc_desired(self, context, output):
        st = self.phase_state(context)
        if st.phase == "task":
            q, v, a = evaluate_timed(st.curves, context.get_time(), st.q_switch)
            output.SetFromVector(np.concatenate([q, v, a]))
        elif self._plan_desired.HasValue(context):
            output.SetFromVector(self._plan_desired.Eval(context))
        else:
            output.SetFromVector(np.concatenate(at_rest(self._q0)))

    def _on_init(self, context, state):
        if self.switch_time_s <= 0:
            self._switch(context, state)
        else:
            state.get_mutable_abstract_state(int(self._state)).set_value(PhaseState())
        return EventStatus.Succeeded()

    def _on_switch(self, context, state):
        if self.phase_state(context).phase != "task":
            self._switch(context, state)
        return EventStatus.Succeeded()

    def _switch(self, context, state):
        t = context.get_time()
        desired = self._plan_desired.Eval(context) if self._plan_desired.HasValue(context) else None
        q_now = self._q0 if desired is None else np.array(desired[: self._n])
        thetas = tuple(np.array(port.Eval(context), float) for port in self._task_thetas)
        curves, start = [], t
        made, events, report = self._make_task(q_now, thetas)
        for curve in made:
            curves.append(TimedCurve(start, curve))
            start += curve.duration
        found = tuple(dict(t=t, **e) for e in events)
        new = PhaseState("task", t, q_now, tuple(curves), bool(curves), thetas, found, dict(report))
        state.get_mutable_abstract_state(int(self._state)).set_value(new)
