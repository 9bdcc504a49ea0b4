"""Desired trajectory source: [q_d, qd_d, qdd_d] (3 n) from degree-5 Bezier pieces.

A piece is (t_start_s, QuinticBezier, q_end). At time t the latest piece with t_start <= t is
evaluated at t - t_start (after its duration it rests at q_end: the built-in brake). Pieces
live in the context (abstract state), so a planner can append pieces while the diagram runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, Context, LeafSystem

from .bezier import DEGREE, QuinticBezier, _monomial_of_bernstein

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


def _as_pieces(trajectory):
    if isinstance(trajectory, QuinticBezier):
        raise TypeError("pass (QuinticBezier, q_end) or a list of Piece")
    if isinstance(trajectory, tuple) and len(trajectory) == 2 and isinstance(trajectory[0], QuinticBezier):
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


def make_trajectory_source(n: int, trajectory: tuple[QuinticBezier, np.ndarray] | list[Piece]) -> TrajectorySource:
    """TrajectorySource with output 'desired' (3 n); trajectory = (QuinticBezier, q_end) or [Piece]."""
    return TrajectorySource(n, trajectory)
