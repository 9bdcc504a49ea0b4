"""Affine forms (a zonotope-with-ellipsoid arithmetic) for the interval RNEA of interval_dynamics.py.

A quantity x is enclosed as x = c + g . s + [-r, r] where s ranges over a fixed symbol set
S = [-1, 1]^a x ([-1, 1]^b and |s|_2 <= kappa) x {|s|_2 <= 1} (`Layout`: box symbols, capped box
symbols, one Euclidean ball). Linear operations are exact on (c, g); a product adds B(g1) B(g2)
(plus the remainders) to r, with B(g) >= max over S of |g . s|:
B(g) = |g_box|_1 + min(|g_cap|_1, kappa |g_cap|_2) + |g_ball|_2. Dependencies between
the state variables of a time interval (the same joint angle in every rotation, the same tracking
error in qd, qd_a and qdd_a) are kept to first order, where plain intervals count them once per use.
Rounding: every operation adds a bound of its float error to r (a few units of roundoff times the
magnitudes of its operands |c| + |g|_1 + r) and rounds r up.

The symbols of one time interval (`tube_states`): per joint a box symbol for q (its hull), one for
the tracking error e_i = pos_i s_e,i, and the ball symbol of r = eps s_r (|r|_2 <= eps because
1/2 r^T M r <= V_max and M >= sigma_min I; armour.py). The errors are capped jointly too: e solves
de/dt = r - Kr e from e(0) = 0, so Kr_i e_i(t) = int_0^t Kr_i exp(-Kr_i (t - s)) r_i(s) ds and
|Kr e(t)|_2 <= int max_i Kr_i exp(-Kr_i s) ds * eps = kappa(Kr) eps (`filter_gain`), so |s_e|_2 <=
kappa (1.123 for Kr = 5, 5, 5, 5, 7, 7, 7). The tracking state is then exact in (e, r):
qd = qd_d - (r - Kr e), qd_a = qd_d + Kr e, qdd_a = qdd_d + Kr (r - Kr e); the desired hulls over
the time interval and the k box enter as remainders.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.math.intervals import dot_rounding

if TYPE_CHECKING:
    from safesysid.systems.controller.armour import TrackingBounds
    from safesysid.systems.math.intervals import Interval

_U = np.finfo(float).eps


_UP = 1 + 8 * _U


def _mag(x):
    """An upper bound of |c| + |g|_1 + r, carried along (m) instead of recomputed at every operation."""
    if x.m is None:
        x.m = (np.abs(x.c) + np.abs(x.g).sum(-1) + x.r) * (1 + dot_rounding(x.g.shape[-1] + 2))
    return x.m


def filter_gain(kr: ArrayLike) -> float:
    """kappa = int_0^inf max_i kr_i exp(-kr_i t) dt (>= 1), rounded up: the upper envelope of the
    lines log kr_i - kr_i t, integrated piece by piece (int_a^b k e^{-k t} = e^{-k a} - e^{-k b})."""
    ks = np.unique(np.asarray(kr, float))[::-1]  # fastest first: it dominates near t = 0
    t, total, cur = 0.0, 0.0, 0
    while True:
        # next line to overtake the current one (smaller gain, later crossing), earliest first
        cross = [(np.log(ks[cur] / ks[j]) / (ks[cur] - ks[j]), j) for j in range(cur + 1, len(ks)) if ks[j] < ks[cur]]
        cross = [(x, j) for x, j in cross if x > t]
        if not cross:
            total += np.exp(-ks[cur] * t)
            return float(total * (1 + 1e-12))
        x, j = min(cross)
        total += np.exp(-ks[cur] * t) - np.exp(-ks[cur] * x)
        t, cur = x, j


class Layout:
    """Symbol layout: n_box box symbols, then n_cap box symbols with |s|_2 <= kappa, then a ball."""

    def __init__(self, n_box: int, n_cap: int, kappa: float) -> None:
        self.n_box, self.n_cap, self.kappa = n_box, n_cap, kappa


class Affine:
    """c (...), g (..., S), r (...) >= 0 over the symbol set of `layout`."""

    __array_ufunc__ = None  # ndarray op Affine -> Affine's reflected op

    def __init__(
        self, c: np.ndarray, g: np.ndarray, r: np.ndarray, layout: Layout, *, m: np.ndarray | None = None
    ) -> None:
        self.c, self.g, self.r, self.layout, self.m = c, g, r, layout, m
        self._dev = None

    def deviation(self) -> np.ndarray:
        """B(g) + r: the largest |x - c| (cached: a form is often multiplied several times)."""
        if self._dev is None:
            self._dev = self.spread() + self.r
        return self._dev

    @classmethod
    def constant(cls, lo: ArrayLike, hi: ArrayLike, like: Affine) -> Affine:
        """An interval [lo, hi] (no symbols) in the symbol space of `like`."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        c = 0.5 * (lo + hi)
        r = np.maximum(hi - c, c - lo) * (1 + 4 * _U)
        return cls(c, np.zeros(c.shape + (like.g.shape[-1],)), r, like.layout)

    # -- bounds --------------------------------------------------------------------------------
    def spread(self, g: np.ndarray | None = None) -> np.ndarray:
        """B(g) = max over the symbol set of |g . s| (rounded up)."""
        g = self.g if g is None else g
        a, b = self.layout.n_box, self.layout.n_box + self.layout.n_cap
        box = np.abs(g[..., :a]).sum(-1)
        cap = g[..., a:b]
        capped = np.minimum(np.abs(cap).sum(-1), self.layout.kappa * np.sqrt((cap**2).sum(-1)))
        ball = np.sqrt((g[..., b:] ** 2).sum(-1))
        return (box + capped + ball) * (1 + 8 * _U)

    @property
    def rad(self) -> np.ndarray:
        return (self.spread() + self.r) * (1 + 4 * _U)

    @property
    def lo(self) -> np.ndarray:
        return self.c - self.rad

    @property
    def hi(self) -> np.ndarray:
        return self.c + self.rad

    @property
    def mag(self) -> np.ndarray:
        return np.abs(self.c) + self.rad

    @property
    def shape(self) -> tuple[int, ...]:
        return self.c.shape

    # -- arithmetic ----------------------------------------------------------------------------
    def _new(self, c, g, r, m=None):
        return Affine(c, g, r, self.layout, m=m)

    @staticmethod
    def _lift(o, like):
        if isinstance(o, Affine):
            return o
        if hasattr(o, "lo"):  # an interval (_Box)
            return Affine.constant(o.lo, o.hi, like)
        return None

    def __getitem__(self, idx):
        gidx = idx + (slice(None),) if isinstance(idx, tuple) and Ellipsis in idx else idx
        part = self._new(self.c[idx], self.g[gidx], self.r[idx], _mag(self)[idx])
        part._dev = self.deviation()[idx]  # once for the whole form: its parts are multiplied next
        return part

    def __neg__(self):
        return self._new(-self.c, -self.g, self.r, _mag(self))

    def __add__(self, o):
        a = self._lift(o, self)
        if a is None:  # a constant array
            o = np.asarray(o, float)
            m = _mag(self) + np.abs(o)
            return self._new(self.c + o, self.g, (self.r + 2 * _U * m) * _UP, m * _UP)
        m = _mag(self) + _mag(a)
        return self._new(self.c + a.c, self.g + a.g, (self.r + a.r + 2 * _U * m) * _UP, m * _UP)

    __radd__ = __add__

    def __sub__(self, o):
        return self + (-o)

    def __rsub__(self, o):
        return (-self) + o

    def __mul__(self, o):
        a = self._lift(o, self)
        if a is None:  # exact scaling by a constant array, rounding added
            o = np.asarray(o, float)
            m = np.abs(o) * _mag(self)
            return self._new(self.c * o, self.g * o[..., None], (np.abs(o) * self.r + 2 * _U * m) * _UP, m * _UP)
        c1, c2 = self.c, a.c
        b1, b2 = self.deviation(), a.deviation()
        c = c1 * c2
        g = c1[..., None] * a.g + c2[..., None] * self.g
        m = _mag(self) * _mag(a)
        r = np.abs(c1) * a.r + np.abs(c2) * self.r + b1 * b2 + 4 * _U * m
        return self._new(c, g, r * _UP, m * (1 + 16 * _U))

    __rmul__ = __mul__

    def sum(self, axis: int) -> Affine:
        k = self.c.shape[axis]
        gaxis = axis if axis >= 0 else axis - 1
        m = _mag(self).sum(axis)
        rounding = dot_rounding(k)  # of the k-term float sums (c, r, m)
        return self._new(
            self.c.sum(axis), self.g.sum(gaxis), (self.r.sum(axis) + rounding * m) * _UP, m * (1 + rounding)
        )


def stack(items: Sequence[Affine], axis: int = -1) -> Affine:
    gaxis = axis if axis >= 0 else axis - 1
    return items[0]._new(
        np.stack([x.c for x in items], axis),
        np.stack([x.g for x in items], gaxis),
        np.stack([x.r for x in items], axis),
        np.stack([_mag(x) for x in items], axis),
    )


def cat(items: Sequence[Affine]) -> Affine:
    return items[0]._new(
        np.concatenate([x.c for x in items], -1),
        np.concatenate([x.g for x in items], -2),
        np.concatenate([x.r for x in items], -1),
        np.concatenate([_mag(x) for x in items], -1),
    )


def concat_rows(items: Sequence[Affine]) -> Affine:
    """Affine forms of the same layout concatenated along the first axis."""
    return items[0]._new(
        np.concatenate([x.c for x in items]),
        np.concatenate([x.g for x in items]),
        np.concatenate([x.r for x in items]),
        np.concatenate([_mag(x) for x in items]),
    )


def swap_last(x: Affine) -> Affine:
    """Transpose of the last two (data) axes."""
    return x._new(
        np.swapaxes(x.c, -1, -2), np.swapaxes(x.g, -2, -3), np.swapaxes(x.r, -1, -2), np.swapaxes(_mag(x), -1, -2)
    )


def gather(x: Affine, comp: np.ndarray, sign: np.ndarray, *, shape: tuple[int, ...]) -> Affine:
    """y[..., m] = sign[m] x[..., comp[m]] reshaped to (..., *shape) (exact)."""
    lead = x.c.shape[:-1]
    c = (x.c[..., comp] * sign).reshape(lead + shape)
    g = (x.g[..., comp, :] * sign[:, None]).reshape(lead + shape + (x.g.shape[-1],))
    r = (x.r[..., comp] * np.abs(sign)).reshape(lead + shape)
    return x._new(c, g, r, (_mag(x)[..., comp] * np.abs(sign)).reshape(lead + shape))


def sin_cos(q: Affine) -> tuple[Affine, Affine]:
    """sin q, cos q as affine forms: first-order Taylor at the centre, |remainder| <= B(g)^2 / 2 + r."""
    s, c = np.sin(q.c), np.cos(q.c)
    b = q.spread() + q.r
    rem = (0.5 * b * b + q.r + 4 * _U * (1 + np.abs(q.c))) * (1 + 4 * _U)
    return (
        q._new(s, c[..., None] * q.g, rem),
        q._new(c, -s[..., None] * q.g, rem),
    )


def tube_states(
    q_box: Interval, vd: Interval, ad: Interval, bounds: TrackingBounds
) -> tuple[Affine, Affine, Affine, Affine]:
    """Affine (q, qd, qd_a, qdd_a) of the time intervals: q_box (Interval (N, n), the planner's q
    hull with the tube), vd, ad (Intervals (N, n): the DESIRED velocity and acceleration hulls,
    no tube) and the controller's TrackingBounds. Symbols: [q (n), e (n) | r (n, ball)]."""
    n = q_box.lo.shape[1]
    nsym = 3 * n
    eye = np.eye(n)
    # kr >= Kr by the outward factor of TrackingBounds (~1e-15 relative): s_e = Kr e / (kr pos) keeps
    # |s_e| <= 1 and Kr e exact; Kr^2 e differs from kr^2 pos s_e by < 1e-12 kr^2 pos (remainder).
    kr = bounds.qdd_a / (2 * bounds.eps) if bounds.eps > 0 else np.zeros(n)
    pos = bounds.position
    # s_e = Kr e / (kr pos) and kr pos >= eps: |s_e|_2 <= |Kr e|_2 / eps <= filter_gain(Kr) (Kr <= kr)
    layout = Layout(n, n, filter_gain(kr))

    def form(centre, rad_box, g_e, g_r, rem):
        nb = centre.shape[0]
        g = np.zeros((nb, n, nsym))
        g[:, :, :n] = eye * rad_box[:, :, None] if rad_box is not None else 0.0
        g[:, :, n : 2 * n] = g_e
        g[:, :, 2 * n :] = g_r
        return Affine(centre, g, rem * (1 + 4 * _U) + 4 * _U * np.abs(centre), layout)

    def mid_rad(x):
        c = 0.5 * (x.lo + x.hi)
        return c, np.maximum(x.hi - c, c - x.lo) * (1 + 4 * _U)

    qc, qr = mid_rad(q_box)
    vc, vr = mid_rad(vd)
    ac, ar = mid_rad(ad)
    zero = np.zeros((n, n))
    ke = eye * (kr * pos)  # Kr e, per symbol s_e
    er = eye * bounds.eps  # r, per symbol s_r
    q = form(qc, qr, zero, zero, np.zeros_like(qc))
    v = form(vc, None, ke, -er, vr)  # qd_d - r + Kr e
    va = form(vc, None, ke, zero, vr)  # qd_d + Kr e
    aa = form(
        ac, None, -eye * (kr * kr * pos), eye * (kr * bounds.eps), ar + 1e-12 * kr * kr * pos
    )  # qdd_d + Kr r - Kr^2 e
    return q, v, va, aa
