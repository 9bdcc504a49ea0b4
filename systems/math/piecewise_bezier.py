"""Piecewise degree-5 Bézier curves of the task trajectory (systems/task/trajectory.py): K pieces
of equal duration, their sampling basis, the exact jerk cost, and the affine parametrization of
every curve at rest at both ends and C2 at the junctions."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from math import comb

import numpy as np
from safesysid.systems.math.bezier import _bernstein, _difference, _monomial_of_bernstein

DEGREE = 5
_POWERS = np.arange(DEGREE + 1)


# ---------------------------------------------------------------------------------------------
# Piecewise Bézier
# ---------------------------------------------------------------------------------------------
@dataclass
class PiecewiseBezier:
    """K degree-5 pieces of equal duration; control_points (K, 6, n)."""

    control_points: np.ndarray
    piece_duration: float

    @property
    def num_pieces(self) -> int:
        return self.control_points.shape[0]

    @property
    def duration(self) -> float:
        return self.num_pieces * self.piece_duration

    def evaluate(self, t: float | np.ndarray, orders: int = 3) -> list[np.ndarray]:
        """[q, dq/dt, d2q/dt2, ...] (orders + 1 arrays (len(t), n)); at rest outside [0, T]."""
        t = np.atleast_1d(np.asarray(t, float))
        x = self.control_points.reshape(-1, self.control_points.shape[-1])
        out = [basis(t, self.num_pieces, self.piece_duration, order=k) @ x for k in range(orders + 1)]
        outside = ((t < 0) | (t > self.duration))[:, None]
        return [out[0]] + [np.where(outside, 0.0, d) for d in out[1:]]

    def evaluate_at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, dq/dt, d2q/dt2) at one t: evaluate's values (to rounding) at a 1 kHz loop's cost
        (each piece's monomial coefficients, computed once; evaluate builds the basis each call)."""
        c0, c1, c2 = self._monomials
        t_in = min(max(t, 0.0), self.duration)
        k = min(int(t_in // self.piece_duration), self.num_pieces - 1)
        pw = (t_in / self.piece_duration - k) ** _POWERS
        if t < 0 or t > self.duration:
            return pw @ c0[k], np.zeros(c0.shape[-1]), np.zeros(c0.shape[-1])
        return pw @ c0[k], pw[:-1] @ c1[k], pw[:-2] @ c2[k]

    @cached_property
    def _monomials(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per piece, the coefficients of s^j (s: the piece's own time in [0, 1]) of q, dq/dt, d2q/dt2."""
        c0 = np.einsum("jk,pkn->pjn", _monomial_of_bernstein(DEGREE), self.control_points)
        d = self.piece_duration
        c1 = c0[:, 1:] * _POWERS[1:, None] / d
        c2 = c0[:, 2:] * (_POWERS[2:] * (_POWERS[2:] - 1))[:, None] / d**2
        return c0, c1, c2

    def to_dict(self) -> dict:
        return {"piece_duration_s": self.piece_duration, "control_points_rad": self.control_points.tolist()}

    @classmethod
    def from_dict(cls, doc: dict) -> PiecewiseBezier:
        return cls(np.asarray(doc["control_points_rad"], float), float(doc["piece_duration_s"]))


def basis(t: float | np.ndarray, num_pieces: int, piece_duration: float, *, order: int = 0) -> np.ndarray:
    """B (len(t), 6K): the order-th time derivative of the curve at t is B @ X (X: (6K, n))."""
    t = np.clip(np.atleast_1d(np.asarray(t, float)), 0.0, num_pieces * piece_duration)
    piece = np.minimum((t // piece_duration).astype(int), num_pieces - 1)
    s = t / piece_duration - piece
    local = _bernstein(DEGREE - order, s) @ _difference(np.eye(DEGREE + 1), order) / piece_duration**order
    out = np.zeros((len(t), (DEGREE + 1) * num_pieces))
    for k in range(DEGREE + 1):
        out[np.arange(len(t)), 6 * piece + k] = local[:, k]
    return out


def jerk_gram(num_pieces: int, piece_duration: float) -> np.ndarray:
    """Q (6K, 6K): sum_j int |jerk_j|^2 dt = sum_j x_j^T Q x_j (exact)."""
    d3 = _difference(np.eye(DEGREE + 1), 3) / piece_duration**3  # (3, 6): jerk control points
    g = np.array([[comb(2, i) * comb(2, j) / (5.0 * comb(4, i + j)) for j in range(3)] for i in range(3)])
    block = piece_duration * d3.T @ g @ d3  # int over the piece: T int_0^1 ds
    return np.kron(np.eye(num_pieces), block)


@dataclass
class Parametrization:
    """X = N Z + g_s q_start^T + g_g q_goal^T: every control-point matrix of K pieces with rest at
    both ends and C0, C1, C2 junctions (equal durations, so equal control-point differences)."""

    null: np.ndarray  # (6K, r)
    g_start: np.ndarray  # (6K,)
    g_goal: np.ndarray  # (6K,)

    @classmethod
    def make(cls, num_pieces: int) -> Parametrization:
        from scipy.linalg import null_space

        m = 6 * num_pieces
        rows, rhs = [], []  # rhs: 0 none, 1 q_start, 2 q_goal

        def row(entries, side=0):
            r = np.zeros(m)
            for idx, val in entries:
                r[idx] += val
            rows.append(r)
            rhs.append(side)

        for k in range(3):  # rest at the start: P0 = P1 = P2 = q_start; at the end likewise
            row([(k, 1.0)], 1)
            row([(m - 1 - k, 1.0)], 2)
        for p in range(num_pieces - 1):
            a, b = 6 * p, 6 * (p + 1)
            for order in range(3):  # derivative `order` at s = 1 of piece p equals it at s = 0 of p + 1
                end, start = _difference(np.eye(6), order)[[-1, 0]]
                row([(a + i, end[i]) for i in range(6)] + [(b + i, -start[i]) for i in range(6)])
        e = np.array(rows)
        f = np.array(rhs)
        pinv = np.linalg.pinv(e)
        return cls(null_space(e), pinv @ (f == 1).astype(float), pinv @ (f == 2).astype(float))

    @property
    def r(self) -> int:
        return self.null.shape[1]

    def control_points(self, z: np.ndarray, q_start: np.ndarray, q_goal: np.ndarray) -> np.ndarray:
        return self.null @ z + np.outer(self.g_start, q_start) + np.outer(self.g_goal, q_goal)
