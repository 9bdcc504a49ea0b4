"""Compiled kernels (numba) of the 1 kHz controller path for a serial chain of revolute joints:
the regressors Wp, Wm and the ARMOUR law at ONE sample, the same math as
armour.ControllerDynamics.regressors and armour.armour_control (tests/test_bench.py checks them
equal to 1e-12, and the law's hull against exact rational arithmetic).

Why compiled: at one sample the numpy version spends its time in call overhead (~60 numpy calls,
~70 µs), not arithmetic (~20k flops). The spatial algebra's bilinear maps (I(x), B(v) va and the
energy form, each a constant tensor in armour.py) enter as their few nonzero entries.

Conventions (as armour_fast.FastControllerDynamics): body i's motion transform to the world is
Y_i = L_0(q_0) ... L_i(q_i), L_i linear in (1, sin q_i, 1 - cos q_i) (`local`, (n, 3, 6, 6));
world -> body i is X_i = Y_i^-1, whose transpose is Y_i with its 3 x 3 blocks swapped.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# error_model="numpy": float division follows IEEE as numpy does (the code never divides by 0).
_jit = numba.njit(cache=True, error_model="numpy")
_SWAP = np.array([3, 4, 5, 0, 1, 2])
Vector = np.ndarray  # (n,) float64, contiguous (the kernels do not convert)
Table = tuple  # sparse_bilinear's (m, k, c, value)


def sparse_bilinear(tensor: np.ndarray, width: int = 6) -> Table:
    """(m, k, c, value) of the nonzeros of a bilinear map given as tensor[width m + k, c]
    (y[c] = sum over m, k of a[m] b[k] tensor[width m + k, c]); a linear map (width 1) has k = 0."""
    rows, cols = np.nonzero(tensor)
    return rows // width, rows % width, cols, tensor[rows, cols].astype(float)


@_jit
def _cross_motion(a, b, out):
    """out = a x b (spatial motion vectors [w; u]): [w x b_w; w x b_u + u x b_w]."""
    _cross3(a[:3], b[:3], out[:3])
    _cross3(a[:3], b[3:], out[3:])
    _cross3(a[3:], b[:3], out[3:])


@_jit
def _cross3(x, y, out):
    """out += x x y (3-vectors)."""
    out[0] += x[1] * y[2] - x[2] * y[1]
    out[1] += x[2] * y[0] - x[0] * y[2]
    out[2] += x[0] * y[1] - x[1] * y[0]


@_jit
def _bodies(q, v, va, aa, x, local, screw, gravity):
    """Per body i, in body i's frame: rows [v twist, va twist, x twist, acceleration] (n, 4, 6),
    and s_body[i, j] = X_i S_j for j <= i (0 above): what both regressors are built from."""
    n = q.shape[0]
    body = np.zeros((n, 4, 6))
    s_body = np.zeros((n, n, 6))
    S = np.zeros((n, 6))
    Y, L, link = np.eye(6), np.empty((6, 6)), np.empty((6, 6))
    world = np.zeros((4, 6))  # running twists of v, va, x and acceleration (tree sums of a chain)
    world[3] = gravity
    sva = np.zeros(6)
    for i in range(n):
        s, c = math.sin(q[i]), 1.0 - math.cos(q[i])
        link[:] = local[i, 0] + s * local[i, 1] + c * local[i, 2]  # L_i(q_i)
        for row in range(6):  # Y_i = Y_(i-1) L_i (into L, then swapped); by hand: a BLAS call costs more at 6 x 6
            for col in range(6):
                acc = 0.0
                for d in range(6):
                    acc += Y[row, d] * link[d, col]
                L[row, col] = acc
        Y, L = L, Y
        for row in range(6):
            acc = 0.0
            for d in range(6):
                acc += Y[row, d] * screw[i, d]
            S[i, row] = acc
        # dS_i/dt va_i = V_parent(i) x (S_i va_i): world[0] still holds the parent's twist here.
        sva[:] = S[i] * va[i]
        _cross_motion(world[0], sva, world[3])
        world[0] += S[i] * v[i]
        world[1] += sva
        world[2] += S[i] * x[i]
        world[3] += S[i] * aa[i]
        for col in range(6):  # row vectors times X_i^T (= Y_i, blocks swapped)
            ycol = _SWAP[col]
            for k in range(4):
                acc = 0.0
                for d in range(6):
                    acc += world[k, d] * Y[_SWAP[d], ycol]
                body[i, k, col] = acc
            for j in range(i + 1):
                acc = 0.0
                for d in range(6):
                    acc += S[j, d] * Y[_SWAP[d], ycol]
                s_body[i, j, col] = acc
    return body, s_body


@_jit
def _dot(x, y):
    acc = 0.0
    for k in range(x.shape[0]):
        acc += x[k] * y[k]
    return acc


@_jit
def _linear(x, table, out):
    """out[c] += x[m] value over the table's nonzeros (m, -, c, value)."""
    m, _, c, value = table
    for k in range(m.shape[0]):
        out[c[k]] += x[m[k]] * value[k]


@_jit
def _bilinear(a, b, table, out):
    """out[c] += a[m] b[k] value over the table's nonzeros (m, k, c, value)."""
    m, kk, c, value = table
    for k in range(m.shape[0]):
        out[c[k]] += a[m[k]] * b[kk[k]] * value[k]


@_jit
def _joint_columns(s_body, y, out):
    """out[j, 10 i + l] = (X_i S_j) . y[i, :, l] for j <= i (body i's wrench regressor y (n, 60),
    as 6 x 10, projected on the joints that move it)."""
    n = s_body.shape[0]
    for i in range(n):
        for j in range(i + 1):
            for l in range(10):
                acc = 0.0
                for d in range(6):
                    acc += s_body[i, j, d] * y[i, 10 * d + l]
                out[j, 10 * i + l] = acc


@_jit
def _friction(va, aa, smoothing, out):
    """Wp's friction columns [coulomb(va), va, aa, 1] of each joint (theta's 10 n + 4 j + k)."""
    n = va.shape[0]
    for j in range(n):
        f0 = 10 * n + 4 * j
        out[j, f0] = math.tanh(va[j] / smoothing) if smoothing > 0 else np.sign(va[j])
        out[j, f0 + 1] = va[j]
        out[j, f0 + 2] = aa[j]
        out[j, f0 + 3] = 1.0


@_jit
def chain_regressors(q: Vector, v: Vector, va: Vector, aa: Vector, x: Vector, dynamics: tuple) -> np.ndarray:
    """(2, n, 14 n): [Wp(q, v, va, aa), Wm(q, x)] (armour.ControllerDynamics.regressors);
    dynamics: the robot's constants (armour_fast.FastControllerDynamics.kernel_constants)."""
    n = q.shape[0]
    local, screw, gravity, smoothing, inertia, bilinear, _ = dynamics
    body, s_body = _bodies(q, v, va, aa, x, local, screw, gravity)
    y_p, y_m = np.zeros((n, 60)), np.zeros((n, 60))
    for i in range(n):
        _linear(body[i, 3], inertia, y_p[i])  # I a
        _bilinear(body[i, 0], body[i, 1], bilinear, y_p[i])  # + B(v) va
        _linear(body[i, 2], inertia, y_m[i])  # I x
    out = np.zeros((2, n, 14 * n))
    _joint_columns(s_body, y_p, out[0])
    _joint_columns(s_body, y_m, out[1])
    _friction(va, aa, smoothing, out[0])
    for j in range(n):
        out[1, j, 10 * n + 4 * j + 2] = x[j]  # armature
    return out


@_jit
def chain_passivity_energy(q: Vector, v: Vector, va: Vector, aa: Vector, r: Vector, dynamics: tuple) -> np.ndarray:
    """(n + 1, 14 n): rows 0..n-1 Wp(q, v, va, aa), row n r^T Wm(q, r) (2 x the kinetic energy of
    r as a function of theta: per body r_b^T I r_b, without forming Wm); dynamics as chain_regressors."""
    n = q.shape[0]
    local, screw, gravity, smoothing, inertia, bilinear, energy = dynamics
    body, s_body = _bodies(q, v, va, aa, r, local, screw, gravity)
    y_p = np.zeros((n, 60))
    out = np.zeros((n + 1, 14 * n))
    for i in range(n):
        _linear(body[i, 3], inertia, y_p[i])
        _bilinear(body[i, 0], body[i, 1], bilinear, y_p[i])
        _bilinear(body[i, 2], body[i, 2], energy, out[n, 10 * i : 10 * i + 10])
    _joint_columns(s_body, y_p, out)
    _friction(va, aa, smoothing, out)
    for j in range(n):
        out[n, 10 * n + 4 * j + 2] = r[j] * r[j]  # armature
    return out


@_jit
def armour_law(
    q: Vector,
    v: Vector,
    q_d: Vector,
    qd_d: Vector,
    qdd_d: Vector,
    Kr: Vector,
    continuous: np.ndarray,
    alpha: float,
    V_max: float,
    mid_theta0: np.ndarray,
    spread: Vector,
    up: float,
    tiny_r: float,
    dynamics: tuple,
) -> tuple:
    """armour.armour_control for a chain, with the box given as mid_theta0 (p, 2) = [box centre,
    theta0] and `spread` (p,) = outward (radius + rounding allowance per unit |a|), as
    armour_fast.FastArmourLaw caches them. Returns (u, tau_nom, v, w_bar, V_bar, h, lam, e, edot,
    qd_a, qdd_a, r)."""
    n = q.shape[0]
    e = q_d - q
    for j in range(n):
        if continuous[j]:
            e[j] = (e[j] + math.pi) % (2 * math.pi) - math.pi  # wrapped to (-pi, pi] as armour.wrap_error
    edot = qd_d - v
    ke = Kr * e
    r = edot + ke
    qd_a, qdd_a = qd_d + ke, qdd_d + Kr * edot
    a = chain_passivity_energy(q, v, qd_a, qdd_a, r, dynamics)
    # The interval product a [theta] (intervals.matmul): mid +- spread, outward.
    lo, hi, tau_nom = np.empty(n + 1), np.empty(n + 1), np.empty(n)
    for k in range(n + 1):
        mid = nom = rad = 0.0
        for c in range(a.shape[1]):
            mid += a[k, c] * mid_theta0[c, 0]
            nom += a[k, c] * mid_theta0[c, 1]
            rad += abs(a[k, c]) * spread[c]
        lo[k], hi[k] = np.nextafter(mid - rad, -np.inf), np.nextafter(mid + rad, np.inf)
        if k < n:
            tau_nom[k] = nom
    w_bar = np.empty(n)
    for k in range(n):
        w_bar[k] = max(np.nextafter(max(hi[k] - tau_nom[k], tau_nom[k] - lo[k]), np.inf), 0.0)
    V_bar = 0.5 * hi[n]
    h = V_max - V_bar
    # armour.robust_input: v = lambda r / |r|, lambda = max(0, -alpha h / |r| + |w_bar|).
    norm_r = math.sqrt(_dot(r, r))
    v_rob, lam = np.zeros(n), 0.0
    if norm_r >= tiny_r:
        lam = max(0.0, -alpha * h / norm_r + math.sqrt(_dot(w_bar, w_bar)) * up)
        v_rob = lam * r / norm_r
    return tau_nom + v_rob, tau_nom, v_rob, w_bar, V_bar, h, lam, e, edot, qd_a, qdd_a, r
