"""Vectorized interval arithmetic with outward rounding (numpy arrays of [lo, hi]).

Hand-rolled because the maintained Python interval packages (pyinterval, mpmath.iv) are scalar
and thousands of times too slow for the per-sample, per-parameter boxes we propagate. Every
operation rounds its result one ulp outward, so each returned box contains the exact set.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def _down(x):
    return np.nextafter(x, -np.inf)


def _up(x):
    return np.nextafter(x, np.inf)


class Interval:
    __array_priority__ = 1000  # numpy defers binary operators to us

    def __init__(self, lo, hi=None):
        lo = np.asarray(lo, float)
        hi = lo if hi is None else np.asarray(hi, float)
        self.lo, self.hi = np.broadcast_arrays(lo, hi)
        if np.any(self.lo > self.hi):
            raise ValueError("interval with lower bound above upper bound")

    # -- constructors / views ---------------------------------------------------------------------
    @classmethod
    def from_mid_rad(cls, mid: ArrayLike, rad: ArrayLike) -> Interval:
        mid, rad = np.asarray(mid, float), np.abs(np.asarray(rad, float))
        return cls(_down(mid - rad), _up(mid + rad))

    @property
    def mid(self) -> np.ndarray:
        return 0.5 * (self.lo + self.hi)

    @property
    def rad(self) -> np.ndarray:
        return _up(0.5 * (self.hi - self.lo))

    @property
    def width(self) -> np.ndarray:
        return self.hi - self.lo

    @property
    def mag(self) -> np.ndarray:
        """max |x| over the interval."""
        return np.maximum(np.abs(self.lo), np.abs(self.hi))

    @property
    def shape(self) -> tuple[int, ...]:
        return self.lo.shape

    def __getitem__(self, idx):
        return Interval(self.lo[idx], self.hi[idx])

    def __setitem__(self, idx, value):
        value = as_interval(value)
        self.lo = self.lo.copy()
        self.hi = self.hi.copy()
        self.lo[idx], self.hi[idx] = value.lo, value.hi

    def __len__(self):
        return len(self.lo)

    def __repr__(self):
        return f"Interval(lo={self.lo!r}, hi={self.hi!r})"

    def contains(self, x: ArrayLike, tol: float = 0.0) -> np.ndarray:
        x = np.asarray(x, float)
        return (self.lo - tol <= x) & (x <= self.hi + tol)

    def intersect(self, other: Interval) -> Interval:
        """Intersection; raises ValueError when it would be empty."""
        other = as_interval(other)
        return Interval(np.maximum(self.lo, other.lo), np.minimum(self.hi, other.hi))

    def hull(self, other: Interval) -> Interval:
        other = as_interval(other)
        return Interval(np.minimum(self.lo, other.lo), np.maximum(self.hi, other.hi))

    # -- arithmetic ----------------------------------------------------------------------------
    def __neg__(self):
        return Interval(-self.hi, -self.lo)

    def __add__(self, other):
        o = as_interval(other)
        return Interval(_down(self.lo + o.lo), _up(self.hi + o.hi))

    __radd__ = __add__

    def __sub__(self, other):
        o = as_interval(other)
        return Interval(_down(self.lo - o.hi), _up(self.hi - o.lo))

    def __rsub__(self, other):
        return as_interval(other) - self

    def __mul__(self, other):
        o = as_interval(other)
        prods = np.stack(np.broadcast_arrays(self.lo * o.lo, self.lo * o.hi, self.hi * o.lo, self.hi * o.hi))
        return Interval(_down(prods.min(0)), _up(prods.max(0)))

    __rmul__ = __mul__

    def square(self) -> Interval:
        lo2, hi2 = self.lo**2, self.hi**2
        low = np.where((self.lo <= 0) & (self.hi >= 0), 0.0, np.minimum(lo2, hi2))
        return Interval(_down(low), _up(np.maximum(lo2, hi2)))

    def sum(self, axis: int | None = None) -> Interval:
        k = self.lo.size if axis is None else self.lo.shape[axis]
        err = dot_rounding(k) * self.mag.sum(axis)  # the float sums' error (dot_rounding)
        return Interval(_down(self.lo.sum(axis) - err), _up(self.hi.sum(axis) + err))


def dot_rounding(k: int) -> float:
    """c such that c * (|a| . mag) bounds the rounding of a mid-radius product of length k: the
    float dot products a . mid and |a| . rad each differ from the exact ones by at most
    gamma_k |a| . mag in any summation order (Higham, Accuracy and Stability of Numerical
    Algorithms, 2nd ed., eq. 3.5: gamma_k = k u / (1 - k u), u = eps / 2), so 2 gamma_k <=
    k eps (1 + k eps); the midpoint's own rounding adds eps / 2. (k + 2) eps covers all of them with
    room for the rounding of c (|a| . mag) itself while k (k + 2) eps <= 1 (k <= 6e7), barring
    underflow (products below 1e-308)."""
    return (k + 2) * np.finfo(float).eps


def as_interval(x: Interval | ArrayLike) -> Interval:
    return x if isinstance(x, Interval) else Interval(x, x)


def matmul(a: np.ndarray, x: Interval) -> Interval:
    """Point matrix (..., m, k) times interval vectors/matrices (..., k[, p]): exact hull, outward.

    The product is linear in x, so mid/radius form is exact up to rounding (dot_rounding).
    """
    x = as_interval(x)
    a = np.asarray(a, float)
    mid = a @ x.mid
    rad = np.abs(a) @ x.rad
    err = dot_rounding(a.shape[-1]) * (np.abs(a) @ x.mag)  # rounding of the float products
    return Interval(_down(mid - rad - err), _up(mid + rad + err))


def sin(x: Interval) -> Interval:
    return _trig(x, np.sin, 0.5 * np.pi)


def cos(x: Interval) -> Interval:
    return _trig(x, np.cos, 0.0)


def _trig(x, f, peak):
    """sin/cos over intervals: endpoint values plus any interior extremum (peak + k pi)."""
    x = as_interval(x)
    lo, hi = x.lo, x.hi
    vals = np.stack([f(lo), f(hi)])
    out_lo, out_hi = vals.min(0), vals.max(0)
    # Maxima of f at peak + 2k pi, minima at peak + pi + 2k pi.
    k_max = np.ceil((lo - peak) / (2 * np.pi))
    has_max = peak + 2 * np.pi * k_max <= hi
    k_min = np.ceil((lo - peak - np.pi) / (2 * np.pi))
    has_min = peak + np.pi + 2 * np.pi * k_min <= hi
    out_hi = np.where(has_max, 1.0, out_hi)
    out_lo = np.where(has_min, -1.0, out_lo)
    pad = 2 * np.finfo(float).eps  # libm sin/cos are within 1 ulp
    return Interval(np.maximum(out_lo - pad, -1.0), np.minimum(out_hi + pad, 1.0))
