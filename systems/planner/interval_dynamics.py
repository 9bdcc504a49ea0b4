"""Interval dynamics for the planner's torque certificate (split from reachability.py: this is the
torque concern, reachability.py the kinematics, joint limits and collision concern).

Item 4 of reachability.py's docstring: the commanded input of the ARMOUR law is
u = W_p(q, qd, qd_a, qdd_a) theta0 + v with |v_j| <= lambda <= ||w_bar||_2 + (alpha/2) eps mu(q) on
the tube (armour.robust_gain_bound), w_bar_i <= sum_k |W_p,ik| d_k. An interval evaluation of the
passivity regressor (interval RNEA in local frames, outward rounded) over the state box of a time
interval bounds sup |u_j| rigorously (`interval_passivity_regressor`; the bounds themselves:
torque_certificate.py); `interval_mass_spread` bounds mu over a configuration box.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.controller.armour import (
    spectral_bound,
)
from safesysid.systems.math.intervals import Interval, _down, _up, dot_rounding
from safesysid.systems.model import regressors
from safesysid.systems.planner import affine_forms as aff
from safesysid.systems.planner.affine_forms import Affine

if TYPE_CHECKING:
    from safesysid.systems.model.robot_model import RobotModel

# ---------------------------------------------------------------------------------------------
# Interval passivity regressor (local-frame RNEA over interval states), torque bound
# ---------------------------------------------------------------------------------------------


_REL = 5e-16  # > 2 units of roundoff: |fl(x) - x| <= u |x|, and the inflation step itself rounds


def _dn(x):
    """Cheap outward rounding (faster than nextafter): x - (5e-16 |x| + tiny) <= exact value."""
    return x - (np.abs(x) * _REL + 1e-300)


def _upr(x):
    return x + (np.abs(x) * _REL + 1e-300)


class _Box(Interval):
    """intervals.Interval for the RNEA below with cheaper outward rounding and no validation
    (measured: * 210 us vs 560 us, + 115 vs 355 us on (64, 10, 6)); sums add the k*eps*sum|x|
    accumulation bound. mid, mag, shape are Interval's."""

    def __init__(self, lo, hi=None):
        self.lo = np.asarray(lo, float)
        self.hi = self.lo if hi is None else np.asarray(hi, float)

    @property
    def rad(self):
        return _upr(0.5 * (self.hi - self.lo))

    def __getitem__(self, idx):
        return _Box(self.lo[idx], self.hi[idx])

    def __neg__(self):
        return _Box(-self.hi, -self.lo)

    def __add__(self, o):
        if isinstance(o, Affine):
            return NotImplemented
        if isinstance(o, _Box):
            return _Box(_dn(self.lo + o.lo), _upr(self.hi + o.hi))
        return _Box(_dn(self.lo + o), _upr(self.hi + o))

    __radd__ = __add__

    def __sub__(self, o):
        if isinstance(o, Affine):
            return NotImplemented
        if isinstance(o, _Box):
            return _Box(_dn(self.lo - o.hi), _upr(self.hi - o.lo))
        return _Box(_dn(self.lo - o), _upr(self.hi - o))

    def __mul__(self, o):
        if isinstance(o, Affine):
            return NotImplemented
        if isinstance(o, _Box):
            p1, p2, p3, p4 = self.lo * o.lo, self.lo * o.hi, self.hi * o.lo, self.hi * o.hi
            return _Box(
                _dn(np.minimum(np.minimum(p1, p2), np.minimum(p3, p4))),
                _upr(np.maximum(np.maximum(p1, p2), np.maximum(p3, p4))),
            )
        p1, p2 = self.lo * o, self.hi * o
        return _Box(_dn(np.minimum(p1, p2)), _upr(np.maximum(p1, p2)))

    __rmul__ = __mul__

    def sum(self, axis):
        k = self.lo.shape[axis]
        err = dot_rounding(k) * self.mag.sum(axis)
        return _Box(_dn(self.lo.sum(axis) - err), _upr(self.hi.sum(axis) + err))


def _stack(items, axis=-1):
    if isinstance(items[0], Affine):
        return aff.stack(items, axis)
    return _Box(np.stack([x.lo for x in items], axis), np.stack([x.hi for x in items], axis))


# Interval twins of regressors.py's cross products (same formulas on _Box; exact per component).
_NEXT, _PREV = [1, 2, 0], [2, 0, 1]


def _cross(a, b):
    """Interval cross product over the last axis (length 3): component i is
    a[i+1] b[i+2] - a[i+2] b[i+1], all three at once (the same products, three times fewer calls)."""
    return a[..., _NEXT] * b[..., _PREV] - a[..., _PREV] * b[..., _NEXT]


def _matvec(m, x):
    """(..., 3, 3) interval matrix times (..., 3) interval vector."""
    return (m * x[..., None, :]).sum(-1)


def _tmatvec(m, x):
    """m^T x."""
    return (m * x[..., :, None]).sum(-2)


def _motion_cross(v, m):
    w, u = v[..., :3], v[..., 3:]
    return _cat([_cross(w, m[..., :3]), _cross(w, m[..., 3:]) + _cross(u, m[..., :3])])


def _force_cross(v, f):
    w, u = v[..., :3], v[..., 3:]
    return _cat([_cross(w, f[..., :3]) + _cross(u, f[..., 3:]), _cross(w, f[..., 3:])])


def _cat(items):
    if isinstance(items[0], Affine):
        return aff.cat(items)
    return _Box(np.concatenate([x.lo for x in items], -1), np.concatenate([x.hi for x in items], -1))


def signed_selection(tensor: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(comp, sign) such that x @ tensor.reshape(k, -1) == x[..., comp] * sign, for a constant
    linear map (k, ...) whose every output entry is +-one input component or 0 (K(x), x x*):
    a gather instead of a product, exact, any dtype, interval-friendly."""
    flat = np.asarray(tensor, float).reshape(len(tensor), -1)
    if not (np.all(np.isin(flat, (-1.0, 0.0, 1.0))) and np.all((flat != 0).sum(0) <= 1)):
        raise ValueError("not a signed selection")
    return np.abs(flat).argmax(0), flat.sum(0)


# K(x) of regressors.inertia_times, transposed to (..., 10, 6): column c of the 6x10 regressor is [..., c, :].
_K_COMP, _K_SIGN = signed_selection(np.swapaxes(regressors.inertia_times(np.eye(6)), 1, 2))


def _inertia_times(x):
    """Interval K(x) stored as (..., 10, 6) (exact: every entry is +-one component of x)."""
    if isinstance(x, Affine):
        return aff.gather(x, _K_COMP, _K_SIGN, shape=(10, 6))
    lo, hi = x.lo[..., _K_COMP], x.hi[..., _K_COMP]
    shape = x.shape[:-1] + (10, 6)
    return _Box(
        np.where(_K_SIGN > 0, lo, np.where(_K_SIGN < 0, -hi, 0.0)).reshape(shape),
        np.where(_K_SIGN > 0, hi, np.where(_K_SIGN < 0, -lo, 0.0)).reshape(shape),
    )


def _body_wrench_regressor(v, va, a):
    """Interval Y (..., 10, 6) with Y theta = I a + B(v) va (regressors.body_wrench_regressor)."""
    kv, kva = _inertia_times(v), _inertia_times(va)
    v_, va_ = v[..., None, :], va[..., None, :]
    return _inertia_times(a) + 0.5 * (
        _force_cross(v_, kva) + _force_cross(va_, kv) - _inertia_times(_motion_cross(v, va))
    )


def _joint_transforms(tree, q):
    """Interval E (N, n, 3, 3) (parent->child rotation of coordinates) and r (N, n, 3) (child
    origin in parent coords) of each joint, entries affine in sin q, cos q (Rodrigues)."""
    n = tree.n
    s, c = _sin_cos(q)
    es, rs = [], []
    for i in range(n):
        rp, tp = tree.X_parent_joint[i, :3, :3], tree.X_parent_joint[i, :3, 3]
        rc, tc = tree.X_joint_child[i, :3, :3], tree.X_joint_child[i, :3, 3]
        if tree.prismatic[i]:
            rot = _Box(np.broadcast_to(rp @ rc, (q.shape[0], 3, 3)))
            pos = q[:, i, None] * (rp @ tree.axis[i]) + (tp + rp @ tc)
        else:
            k = regressors.skew(tree.axis[i])
            # R_parent_child = rp (I + s K + (1 - c) K^2) rc = A0 + s A1 + c A2
            a0 = rp @ (np.eye(3) + k @ k) @ rc
            a1 = rp @ k @ rc
            a2 = -rp @ k @ k @ rc
            si, ci = s[:, i, None, None], c[:, i, None, None]
            rot = _affine3(a0, a1, a2, si, ci)
            b0 = tp + rp @ (np.eye(3) + k @ k) @ tc
            b1 = rp @ k @ tc
            b2 = -rp @ k @ k @ tc
            pos = _affine3(b0, b1, b2, s[:, i, None], c[:, i, None])
        # E = R_parent_child^T: child coords of a parent-coords vector.
        es.append(
            aff.swap_last(rot)
            if isinstance(rot, Affine)
            else _Box(np.swapaxes(rot.lo, -1, -2), np.swapaxes(rot.hi, -1, -2))
        )
        rs.append(pos)
    return _stack(es, 1), _stack(rs, 1)


def _affine3(a0, a1, a2, s, c):
    """a0 + s a1 + c a2 with interval s, c (exact per entry: s, c independent), outward."""
    if isinstance(s, Affine):  # s, c share the joint's symbol: keep it
        return s * a1 + c * a2 + a0
    mid = a0 + s.mid * a1 + c.mid * a2
    rad = np.abs(a1) * s.rad + np.abs(a2) * c.rad
    err = dot_rounding(3) * (np.abs(a0) + np.abs(a1) * s.mag + np.abs(a2) * c.mag)  # mid-radius, 3 terms
    return _Box(_down(mid - rad - err), _up(mid + rad + err))


def _sin_cos(q):
    from safesysid.systems.math import intervals

    if isinstance(q, Affine):
        return aff.sin_cos(q)

    s, c = intervals.sin(Interval(q.lo, q.hi)), intervals.cos(Interval(q.lo, q.hi))
    return _Box(s.lo, s.hi), _Box(c.lo, c.hi)


def _to_child(e, r, x):
    """Motion vector from parent to child coordinates: w' = E w, u' = E (u - r x w)."""
    w, u = x[..., :3], x[..., 3:]
    return _cat([_matvec(e, w), _matvec(e, u - _cross(r, w))])


def _force_to_parent(e, r, f):
    """Force vector from child to parent coordinates: f_p = E^T f, n_p = E^T n + r x f_p."""
    n_, f_ = f[..., :3], f[..., 3:]
    fp = _tmatvec(e, f_)
    return _cat([_tmatvec(e, n_) + _cross(r, fp), fp])


def _joint_screws(tree):
    """Joint motion subspaces (n, 6) in child-body coordinates (constant)."""
    s_local = np.zeros((tree.n, 6))
    for i in range(tree.n):
        rc, tc = tree.X_joint_child[i, :3, :3], tree.X_joint_child[i, :3, 3]
        ax = tree.axis[i]
        if tree.prismatic[i]:
            s_local[i, 3:] = rc.T @ ax
        else:
            # axis through the joint origin, which sits at -rc^T tc in child coordinates
            w = rc.T @ ax
            s_local[i, :3] = w
            s_local[i, 3:] = np.cross(-rc.T @ tc, w)
    return s_local


def interval_body_jacobians(tree: regressors.KinematicTree, q: Interval) -> Interval:
    """Interval body Jacobians (N, n_bodies, n, 6): [row, i, j] = twist of body i (its own
    coordinates) per unit velocity of joint j, over the configuration boxes q (Interval (N, n));
    the velocity pass of the local-frame RNEA below with one unit velocity per joint at once."""
    n = tree.n
    q = _Box(q.lo, q.hi)
    nsamp = q.shape[0]
    e, r = _joint_transforms(tree, q)
    s_local = _joint_screws(tree)
    unit = np.eye(n)[None, :, :, None]  # [., j, i, .] = 1 when j == i
    jac = [None] * n
    for i in range(n):
        own = _Box(np.broadcast_to(unit[:, :, i] * s_local[i], (nsamp, n, 6)))
        par = tree.parent[i]
        jac[i] = own if par < 0 else _to_child(e[:, i, None], r[:, i, None], jac[par]) + own
    return Interval(np.stack([x.lo for x in jac], 1), np.stack([x.hi for x in jac], 1))


# V^T I(theta) V = sum_k theta_k V^T Q_k V for a body-frame spatial inertia (regressors.inertia_times).
_INERTIA_FORMS = np.einsum("bak->kab", regressors.inertia_times(np.eye(6)))  # [k, a, b] = K(e_b)[a, k]
_INERTIA_FORMS = 0.5 * (_INERTIA_FORMS + np.swapaxes(_INERTIA_FORMS, 1, 2))


def interval_mass_spread(
    robot: RobotModel, q: Interval, theta_lo: ArrayLike, theta_hi: ArrayLike, *, per_joint: bool = False
) -> np.ndarray:
    """mu (N,) >= controller.mass_spread(q') for every q' in each configuration box q (Interval (N, n)).

    r^T M r = sum_i (J_i r)^T I_i (J_i r) + sum_j Ia_j r_j^2 (J_i: body Jacobians), so
    dM/dtheta_k = J_i^T Q_k J_i for body i's parameters and e_j e_j^T for Ia_j. With J = Jc + D,
    |D| <= rad(J) over the box: |J^T Q J| <= |Jc^T Q Jc| + |Jc|^T |Q| rad + rad^T |Q| (|Jc| + rad)
    (centred form: the box's width enters to first order). Then as controller.mass_spread:
    mu <= lambda_max(sum_k width_k |dM/dtheta_k|); per_joint: mu_j (N, n) of `joint_spread_bound`."""
    n = robot.n
    width = np.asarray(theta_hi, float) - np.asarray(theta_lo, float)
    jac = interval_body_jacobians(robot.tree, q)
    mid = 0.5 * (jac.lo + jac.hi)
    jc = np.swapaxes(mid, -1, -2)  # (N, n_bodies, 6, n)
    rad = np.swapaxes(_up(np.maximum(jac.hi - mid, mid - jac.lo)), -1, -2)  # |J - Jc| <= rad on the box
    forms = np.abs(_INERTIA_FORMS)
    spread = np.zeros((q.shape[0], n, n))
    for i in range(n):
        w = width[10 * i : 10 * i + 10]
        jci, radi = jc[:, i], rad[:, i]
        centre = np.abs(np.swapaxes(jci, -1, -2)[:, None] @ (_INERTIA_FORMS @ jci[:, None]))  # (N, 10, n, n)
        absj = np.abs(jci)
        first = np.swapaxes(absj, -1, -2)[:, None] @ (forms @ radi[:, None])
        second = np.swapaxes(radi, -1, -2)[:, None] @ (forms @ (absj + radi)[:, None])
        scale = np.swapaxes(absj, -1, -2)[:, None] @ (forms @ absj[:, None])
        bound = centre + first + second + 64 * np.finfo(float).eps * scale  # + rounding of the products
        spread += np.einsum("xkab,k->xab", bound, w)
    ia = width[10 * n + 2 :: 4]
    spread[:, np.arange(n), np.arange(n)] += ia
    return joint_spread_bound(spread) if per_joint else spectral_bound(spread)


def joint_spread_bound(spread: np.ndarray, grid: int = 512) -> np.ndarray:
    """mu_j (N, n) >= max over unit u of |u_j| |u|^T S |u| for entrywise nonnegative S (N, n, n):
    the controller's |v_j| = lambda |u_j| (u = r/|r|), so joint j only sees the barrier excess
    along directions that have a component on j. With |u| = c e_j + s w (w >= 0, unit, _|_ e_j):
    |u|^T S |u| <= c^2 S_jj + 2 c s |S_-j,j| + s^2 lambda_max(S_-j,-j); the max over c = cos(phi)
    is taken on a grid in phi plus the Lipschitz bound of the function (|f'| <= 3a + 6b + 3m).
    Never above lambda_max(S)."""
    spread = 0.5 * (spread + np.swapaxes(spread, -1, -2))
    nb, n, _ = spread.shape
    idx = np.arange(n)
    a = spread[:, idx, idx]
    off = spread.copy()
    off[:, idx, idx] = 0.0
    b = np.nextafter(np.linalg.norm(off, axis=1) * (1 + 1e-12), np.inf)
    m = np.stack([spectral_bound(np.delete(np.delete(spread, j, 1), j, 2)) for j in range(n)], 1)
    phi = np.linspace(0.0, 0.5 * np.pi, grid + 1)
    c, sn = np.cos(phi), np.sin(phi)
    f = c * (c * c * a[..., None] + 2 * c * sn * b[..., None] + sn * sn * m[..., None])
    lip = 3 * a + 6 * b + 3 * m
    top = (f.max(-1) + lip * 0.25 * np.pi / grid) * (1 + 1e-12) + 1e-15
    return np.minimum(top, spectral_bound(spread)[:, None])


def interval_passivity_regressor(
    robot: RobotModel, q: Interval, v: Interval, va: Interval, aa: Interval, *, gravity: bool = True
) -> Interval:
    """Interval Wp (N, n, 14n) enclosing RobotModel.passivity_regressor over boxes q, v, va, aa
    (Intervals (N, n)). Local-frame RNEA: each body's velocity/acceleration from its parent's
    through one interval joint transform; the body wrench regressors carried back up the tree."""
    q, v, va, aa = (_Box(x.lo, x.hi) for x in (q, v, va, aa))
    nsamp, n = q.shape
    lo = np.zeros((nsamp, n, 14 * n))
    hi = np.zeros((nsamp, n, 14 * n))
    for j, cols, x in _regressor_columns(robot, q, v, va, aa, gravity):
        lo[:, j, cols], hi[:, j, cols] = x.lo, x.hi
    return Interval(lo, hi)


def affine_passivity_regressor(
    robot: RobotModel, q: Affine, v: Affine, va: Affine, aa: Affine, *, gravity: bool = True
) -> Affine:
    """Affine Wp (N, n, 14n) (affine_forms.Affine) enclosing RobotModel.passivity_regressor for every
    state of the affine forms q, v, va, aa (N, n) (e.g. affine_forms.tube_states): the same RNEA on
    first-order forms, so each entry keeps its dependence on the shared symbols."""
    nsamp, n = q.shape
    nsym = q.g.shape[-1]
    c, r = np.zeros((nsamp, n, 14 * n)), np.zeros((nsamp, n, 14 * n))
    g = np.zeros((nsamp, n, 14 * n, nsym))
    for j, cols, x in _regressor_columns(robot, q, v, va, aa, gravity):
        x = Affine._lift(x, q)
        c[:, j, cols], g[:, j, cols], r[:, j, cols] = x.c, x.g, x.r
    return Affine(c, g, r, q.layout)


def _regressor_columns(robot, q, v, va, aa, gravity):
    """(joint, columns, values (N, len(columns))) of the passivity regressor, on _Box or Affine states."""
    tree = robot.tree
    n = tree.n
    nsamp = q.shape[0]
    e, r = _joint_transforms(tree, q)
    s_local = _joint_screws(tree)
    g_world = np.concatenate([np.zeros(3), -tree.gravity if gravity else np.zeros(3)])  # base "acceleration"
    vel, vela, acc = [None] * n, [None] * n, [None] * n
    ys = [None] * n
    for i in range(n):
        par = tree.parent[i]
        ei, ri = e[:, i], r[:, i]
        if par < 0:
            v_par = _Box(np.zeros((nsamp, 6)))
            va_par = v_par
            a_par = _Box(np.broadcast_to(g_world, (nsamp, 6)))
        else:
            v_par, va_par, a_par = vel[par], vela[par], acc[par]
        si = _Box(s_local[i])[None]
        vp_c = _to_child(ei, ri, v_par)
        vel[i] = vp_c + si * v[:, i, None]
        vela[i] = _to_child(ei, ri, va_par) + si * va[:, i, None]
        # a_i = X a_par + s aa_i + v_i x s va_i
        acc[i] = _to_child(ei, ri, a_par) + si * aa[:, i, None] + _motion_cross(vel[i], si * va[:, i, None])
        ys[i] = _body_wrench_regressor(vel[i], vela[i], acc[i])  # (N, 10, 6)
    for i in range(n):  # body i's wrench columns carried up to every joint above it
        f = ys[i]
        j = i
        while j >= 0:
            yield j, slice(10 * i, 10 * i + 10), (f * s_local[j][None, None]).sum(-1)  # (N, 10)
            par = tree.parent[j]
            if par < 0:
                break
            f = _force_to_parent(e[:, j, None], r[:, j, None], f)
            j = par
    # Friction columns [Fc, Fv, Ia, beta] per joint.
    vs = robot.coulomb_smoothing
    if vs > 0:
        sgn = _Box(
            np.maximum(_down(np.tanh(va.lo / vs)) - 1e-15, -1.0), np.minimum(_up(np.tanh(va.hi / vs)) + 1e-15, 1.0)
        )
    else:
        sgn = _Box(np.sign(va.lo), np.sign(va.hi))
    for j in range(n):
        base = 10 * n + 4 * j
        for off, x in ((0, sgn), (1, va), (2, aa), (3, _Box(np.ones((nsamp, n))))):
            yield j, slice(base + off, base + off + 1), x[:, j, None]


def merge_rows(box: Interval, group: int) -> Interval:
    """Hull of consecutive groups of `group` rows of an Interval (rows, n) (the last group padded
    with the last row)."""
    rows = box.lo.shape[0]
    pad = (-rows) % group
    lo = np.concatenate([box.lo, np.repeat(box.lo[-1:], pad, 0)]).reshape(-1, group, box.lo.shape[1])
    hi = np.concatenate([box.hi, np.repeat(box.hi[-1:], pad, 0)]).reshape(-1, group, box.hi.shape[1])
    return Interval(lo.min(1), hi.max(1))
