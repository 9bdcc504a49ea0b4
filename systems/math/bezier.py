"""ARMOUR's trajectory family: degree-5 Bézier from (q0, v0, a0) to rest at q_end in T seconds.

Control points (s = t / T): b0 = q0, b1 = q0 + T v0 / 5, b2 = q0 + 2 T v0 / 5 + T^2 a0 / 20,
b3 = b4 = b5 = q_end, so the plan ends at rest (the braking manoeuvre is built in). Every
quantity is affine in q_end = q0 + k_c + k_r * k.

Bounds over a time interval are rigorous: the curve restricted to [t_a, t_b] is again a
Bézier whose control points (a fixed linear map of the original ones) contain it in their
convex hull; the same holds for the derivative curves.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np
from numpy.typing import ArrayLike

DEGREE = 5


def _bernstein(deg, s):
    s = np.asarray(s, float)[:, None]
    i = np.arange(deg + 1)
    return np.array([comb(deg, k) for k in i]) * s**i * (1 - s) ** (deg - i)


def _monomial_of_bernstein(deg):
    """A with Bernstein basis b(s) = A^T [1, s, ..., s^deg]."""
    a = np.zeros((deg + 1, deg + 1))
    for i in range(deg + 1):
        for j in range(i, deg + 1):
            a[j, i] = comb(deg, i) * comb(deg - i, j - i) * (-1) ** (j - i)
    return a


def restriction_matrix(deg: int, s_a: float, s_b: float) -> np.ndarray:
    """R (deg+1, deg+1): control points of the curve on [s_a, s_b] are R @ control points."""
    a = _monomial_of_bernstein(deg)
    # Monomial coefficients c = A P; substitute s = s_a + (s_b - s_a) u.
    sub = np.zeros((deg + 1, deg + 1))
    h = s_b - s_a
    for j in range(deg + 1):
        for m in range(j + 1):
            sub[m, j] = comb(j, m) * s_a ** (j - m) * h**m
    return np.linalg.solve(a, sub @ a)


def _difference(points, order):
    """Control points of the order-th derivative (w.r.t. s) of a Bézier."""
    deg = points.shape[0] - 1
    for r in range(order):
        points = (deg - r) * np.diff(points, axis=0)
    return points


@dataclass
class QuinticBezier:
    q0: np.ndarray
    v0: np.ndarray
    a0: np.ndarray
    duration: float

    def control_points(self, q_end: ArrayLike) -> np.ndarray:
        """(6, n) control points for the end position q_end (n,)."""
        t = self.duration
        q0, v0, a0 = (np.asarray(x, float) for x in (self.q0, self.v0, self.a0))
        q_end = np.broadcast_to(np.asarray(q_end, float), q0.shape)
        return np.stack([q0, q0 + t * v0 / 5, q0 + 2 * t * v0 / 5 + t * t * a0 / 20, q_end, q_end, q_end])

    @staticmethod
    def end_weights(t: ArrayLike, duration: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """d q(t) / d q_end, d qd / d q_end, d qdd / d q_end (each (len(t),)), same for all joints."""
        s = np.clip(np.asarray(t, float) / duration, 0.0, 1.0)
        w = np.array([0, 0, 0, 1, 1, 1.0])
        return (
            _bernstein(5, s) @ w,
            _bernstein(4, s) @ _difference(w[:, None], 1)[:, 0] / duration,
            _bernstein(3, s) @ _difference(w[:, None], 2)[:, 0] / duration**2,
        )

    def evaluate(self, t: ArrayLike, q_end: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q, qd, qdd at times t (clamped to [0, T]; rest at q_end after T): each (len(t), n)."""
        t = np.atleast_1d(np.asarray(t, float))
        s = np.clip(t / self.duration, 0.0, 1.0)
        p = self.control_points(q_end)
        q = _bernstein(5, s) @ p
        qd = _bernstein(4, s) @ _difference(p, 1) / self.duration
        qdd = _bernstein(3, s) @ _difference(p, 2) / self.duration**2
        after = (t > self.duration)[:, None]
        return q, np.where(after, 0.0, qd), np.where(after, 0.0, qdd)

    def interval_bounds(
        self, q_end: ArrayLike, edges_s: ArrayLike
    ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """Rigorous bounds over time intervals [edges[i], edges[i+1]] (seconds).

        Returns three (lo, hi) pairs of arrays (n_intervals, n) for q, qd, qdd.
        """
        edges = np.asarray(edges_s, float) / self.duration
        p = self.control_points(q_end)
        out = []
        for order in range(3):
            pts = _difference(p, order) / self.duration**order
            deg = DEGREE - order
            sub = np.stack([restriction_matrix(deg, a, b) @ pts for a, b in zip(edges[:-1], edges[1:])])
            out.append((sub.min(1), sub.max(1)))
        return tuple(out)
