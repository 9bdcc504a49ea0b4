"""Dynamics regressors of a fixed-base tree of 1-dof joints, vectorized over samples.

All spatial vectors are Plücker [angular; linear]. The forward pass works with twists about
the fixed world origin O expressed in world (so a joint screw S_j, once known, serves every body
below it, and dS_j/dt = V_parent(j) x S_j); each body's wrench is formed in its own frame,
where the regressor of I x is simple, and projected on the joint screws.

Per body i (theta_i in inertial.NAMES order) and joint j an ancestor of i (or i itself):
    standard    W[j, i]   = S_j^T (I_i (A_i - A_g) + V_i x* I_i V_i)        (M qdd + C qd + g)
    passivity   Wp[j, i]  = S_j^T (I_i Aa_i + B(V_i) Va_i)                   (M qdd_a + C(q,qd) qd_a + g)
    momentum    Wm[j, i]  = S_j^T I_i V_i                                    (M qd)
    momentum'   Wc[j, i]  = dS_j^T I_i V_i + S_j^T I_i A_g                   (C^T qd - g)
with B(V) = 1/2 [V x* I - I V x + (I V) xbar] the Christoffel-consistent factorization
(Mdot = C + C^T, so Mdot - 2C is skew: what the robust controller's proof needs).
Friction columns per joint [Fc, Fv, Ia, beta] are appended by `friction_columns`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from safesysid.systems.math.spatial import to_body


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    v = np.asarray(v)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def cross_motion(v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """v x m for spatial motion vectors (..., 6)."""
    w, u = v[..., :3], v[..., 3:]
    return np.concatenate([np.cross(w, m[..., :3]), np.cross(w, m[..., 3:]) + np.cross(u, m[..., :3])], -1)


def cross_force_matrix(v: np.ndarray) -> np.ndarray:
    """(..., 6, 6) matrix of v x* (force cross product)."""
    sw, su = skew(v[..., :3]), skew(v[..., 3:])
    out = np.zeros(v.shape[:-1] + (6, 6))
    out[..., :3, :3] = sw
    out[..., :3, 3:] = su
    out[..., 3:, 3:] = sw
    return out


def inertia_times(x: np.ndarray) -> np.ndarray:
    """K(x) (..., 6, 10) such that I(theta) x = K(x) theta for a body-frame spatial inertia."""
    w, u = x[..., :3], x[..., 3:]
    k = np.zeros(x.shape[:-1] + (6, 10))
    k[..., :3, 1:4] = -skew(u)  # h x u
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    k[..., 0, 4], k[..., 0, 7], k[..., 0, 9] = wx, wy, wz
    k[..., 1, 5], k[..., 1, 7], k[..., 1, 8] = wy, wx, wz
    k[..., 2, 6], k[..., 2, 8], k[..., 2, 9] = wz, wy, wx
    k[..., 3:, 0] = u  # m u
    k[..., 3:, 1:4] = skew(w)  # w x h
    return k


def body_wrench_regressor(v: np.ndarray, va: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Y(v, va, a) with Y theta = I a + B(v) va in the body frame (..., 6, 10)."""
    kv, kva = inertia_times(v), inertia_times(va)
    return inertia_times(a) + 0.5 * (
        cross_force_matrix(v) @ kva + cross_force_matrix(va) @ kv - inertia_times(cross_motion(v, va))
    )


@dataclass(frozen=True)
class KinematicTree:
    """Fixed-base tree of n one-dof joints; body i is the (composite) child of joint i.

    parent[i]: index of the joint whose child carries joint i (-1: the world).
    X_parent_joint[i]: 4x4 pose of joint i's frame F in the parent body frame (world if -1).
    X_joint_child[i]: 4x4 pose of the child body frame in the joint's moving frame M.
    axis[i]: unit axis in F; prismatic[i]: translation instead of rotation.
    """

    parent: np.ndarray
    X_parent_joint: np.ndarray
    X_joint_child: np.ndarray
    axis: np.ndarray
    prismatic: np.ndarray
    gravity: np.ndarray

    @property
    def n(self) -> int:
        return len(self.parent)

    def ancestors(self) -> np.ndarray:
        """Boolean (n, n): [j, i] true when joint j moves body i (j == i included)."""
        anc = np.eye(self.n, dtype=bool)
        for i in range(self.n):
            p = self.parent[i]
            if p >= 0:
                anc[:, i] |= anc[:, p]
        return anc


def _z_to(axis):
    """A rotation A with A e_z = axis (axis unit)."""
    axis = np.asarray(axis, float)
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, axis)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(axis, x), axis], 1)


def _times_const(R, C):
    """(N, 3, 3) @ (3, 3) as one BLAS call."""
    return (R.reshape(-1, 3) @ C).reshape(R.shape)


@dataclass
class Kinematics:
    """Forward kinematics of N samples: body poses and joint screws about O in world."""

    R: np.ndarray  # (N, n, 3, 3) body rotations
    p: np.ndarray  # (N, n, 3) body origins
    S: np.ndarray  # (N, n, 6) joint screws
    V: np.ndarray | None = None  # (N, n, 6) body twists
    Sdot: np.ndarray | None = None  # (N, n, 6) dS/dt


def forward_kinematics(tree: KinematicTree, q: np.ndarray, v: np.ndarray | None = None) -> Kinematics:
    """Poses, screws (and twists, screw rates when v is given) for q (N, n).

    Each joint axis is rotated onto z once (R_F A, A^T X_MC), so the only per-sample rotation is
    an elementwise Rz(q) and the constant products are single matrix multiplications.
    """
    q = np.atleast_2d(np.asarray(q, float))
    nsamp, n = q.shape
    R = np.empty((nsamp, n, 3, 3))
    p = np.empty((nsamp, n, 3))
    S = np.empty((nsamp, n, 6))
    V = None if v is None else np.empty((nsamp, n, 6))
    Sdot = None if v is None else np.empty((nsamp, n, 6))
    v = None if v is None else np.atleast_2d(np.asarray(v, float))
    cos, sin = np.cos(q), np.sin(q)
    for i in range(n):
        par = tree.parent[i]
        xpj, xjc = tree.X_parent_joint[i], tree.X_joint_child[i]
        a = _z_to(tree.axis[i])
        if par < 0:
            r_f = np.broadcast_to(xpj[:3, :3] @ a, (nsamp, 3, 3))
            p_f = np.broadcast_to(xpj[:3, 3], (nsamp, 3))
        else:
            r_f = _times_const(R[:, par], xpj[:3, :3] @ a)
            p_f = p[:, par] + R[:, par] @ xpj[:3, 3]
        z = r_f[:, :, 2]
        if tree.prismatic[i]:
            r_m, p_m = r_f, p_f + z * q[:, i, None]
            S[:, i, :3] = 0.0
            S[:, i, 3:] = z
        else:
            c, s_ = cos[:, i, None], sin[:, i, None]
            r_m = np.stack([r_f[:, :, 0] * c + r_f[:, :, 1] * s_, r_f[:, :, 1] * c - r_f[:, :, 0] * s_, z], -1)
            p_m = p_f
            S[:, i, :3] = z
            S[:, i, 3:] = np.cross(p_f, z)
        R[:, i] = _times_const(r_m, a.T @ xjc[:3, :3])
        p[:, i] = p_m + r_m @ (a.T @ xjc[:3, 3])
        if v is not None:
            if par < 0:
                Sdot[:, i] = 0.0
                V[:, i] = S[:, i] * v[:, i, None]
            else:
                Sdot[:, i] = cross_motion(V[:, par], S[:, i])
                V[:, i] = V[:, par] + S[:, i] * v[:, i, None]
    return Kinematics(R, p, S, V, Sdot)


def _accelerations(tree, kin, a, base):
    """Spatial accelerations about O (N, n, 6) for joint accelerations a, base acceleration."""
    acc = np.empty_like(kin.S)
    for i in range(tree.n):
        par = tree.parent[i]
        prev = base if par < 0 else acc[:, par]
        acc[:, i] = prev + kin.S[:, i] * a[:, i, None]
    return acc


def _velocity_product_terms(tree, kin, va):
    """sum_j dS_j va_j accumulated down the tree (N, n, 6)."""
    out = np.empty_like(kin.S)
    for i in range(tree.n):
        par = tree.parent[i]
        prev = 0.0 if par < 0 else out[:, par]
        out[:, i] = prev + kin.Sdot[:, i] * va[:, i, None]
    return out


def _project(tree, kin, wrench_reg_body, screws_world, bodies=None):
    """Assemble (N, n, 10 b): block of body i = (X_i screw_j)^T Y_i for ancestors j of i.

    bodies: indices of the bodies whose columns are wanted; wrench_reg_body holds their
    6x10 blocks in that order (N, len(bodies), 6, 10).
    """
    nsamp, n = kin.S.shape[:2]
    out = np.zeros((nsamp, n, 10 * len(bodies)))
    anc = tree.ancestors()
    for col, i in enumerate(bodies):
        js = np.flatnonzero(anc[:, i])
        s_body = to_body(kin.R[:, i, None], kin.p[:, i, None], screws_world[:, js])  # (N, k, 6)
        out[:, js, 10 * col : 10 * col + 10] = s_body @ wrench_reg_body[:, col]
    return out


def _selection(tree, bodies):
    return list(range(tree.n)) if bodies is None else list(bodies)


def _gravity_accel(tree, nsamp):
    return np.broadcast_to(np.concatenate([np.zeros(3), -tree.gravity]), (nsamp, 6))


def passivity_regressor(
    tree: KinematicTree,
    q: np.ndarray,
    v: np.ndarray,
    va: np.ndarray,
    aa: np.ndarray,
    *,
    bodies: Sequence[int] | None = None,
) -> np.ndarray:
    """Wp (N, n, 10n): Wp theta = M(q) aa + C(q, v) va + g(q), C Christoffel-consistent.

    With `bodies`, only those bodies' column blocks (N, n, 10 len(bodies)).
    """
    q, v, va, aa = (np.atleast_2d(np.asarray(x, float)) for x in (q, v, va, aa))
    kin = forward_kinematics(tree, q, v)
    nsamp = q.shape[0]
    same = np.array_equal(v, va)
    vel_a = kin.V if same else _accelerations(tree, kin, va, np.zeros((nsamp, 6)))  # Va_i = J_i va
    acc_a = _accelerations(tree, kin, aa, _gravity_accel(tree, nsamp)) + _velocity_product_terms(tree, kin, va)
    sel = _selection(tree, bodies)
    R, p = kin.R[:, sel], kin.p[:, sel]
    vb, ab = to_body(R, p, kin.V[:, sel]), to_body(R, p, acc_a[:, sel])
    if same:  # B(v) v = v x* I v
        y = inertia_times(ab) + cross_force_matrix(vb) @ inertia_times(vb)
    else:
        y = body_wrench_regressor(vb, to_body(R, p, vel_a[:, sel]), ab)
    return _project(tree, kin, y, kin.S, sel)


def standard_regressor(
    tree: KinematicTree, q: np.ndarray, v: np.ndarray, a: np.ndarray, *, bodies: Sequence[int] | None = None
) -> np.ndarray:
    """W (N, n, 10n): W theta = M(q) a + C(q, v) v + g(q) (rigid-body part)."""
    return passivity_regressor(tree, q, v, v, a, bodies=bodies)


def momentum_regressor(
    tree: KinematicTree, q: np.ndarray, v: np.ndarray, *, bodies: Sequence[int] | None = None
) -> np.ndarray:
    """Wm (N, n, 10n): Wm theta = M(q) v."""
    kin = forward_kinematics(tree, q, v)
    sel = _selection(tree, bodies)
    vb = to_body(kin.R[:, sel], kin.p[:, sel], kin.V[:, sel])
    return _project(tree, kin, inertia_times(vb), kin.S, sel)


def momentum_rate_regressor(
    tree: KinematicTree, q: np.ndarray, v: np.ndarray, *, bodies: Sequence[int] | None = None
) -> np.ndarray:
    """Wc (N, n, 10n): Wc theta = C(q, v)^T v - g(q), the rate of M v without input torque."""
    q = np.atleast_2d(np.asarray(q, float))
    kin = forward_kinematics(tree, q, v)
    sel = _selection(tree, bodies)
    R, p = kin.R[:, sel], kin.p[:, sel]
    vb = to_body(R, p, kin.V[:, sel])
    gb = to_body(R, p, np.broadcast_to(-_gravity_accel(tree, q.shape[0])[:, None], vb.shape))
    return _project(tree, kin, inertia_times(vb), kin.Sdot, sel) + _project(tree, kin, inertia_times(gb), kin.S, sel)


def coulomb_shape(v: np.ndarray, smoothing_velocity: float = 0.0) -> np.ndarray:
    """sign(v), or tanh(v / vs) when a smoothing velocity vs > 0 is given (one law for all)."""
    v = np.asarray(v, float)
    if smoothing_velocity > 0:
        return np.tanh(v / smoothing_velocity)
    return np.sign(v)


def friction_columns(
    v: np.ndarray, *, a: np.ndarray | None = None, kind: str = "standard", smoothing_velocity: float = 0.0
) -> np.ndarray:
    """Friction regressor (N, n, 4n), columns per joint [Fc, Fv, Ia, beta].

    standard:  Fc sgn(v) + Fv v + Ia a + beta  (part of tau)
    momentum:  Ia v                            (armature momentum, part of p)
    rate:      -(Fc sgn(v) + Fv v + beta)      (part of dp/dt without input torque)
    """
    v = np.atleast_2d(np.asarray(v, float))
    nsamp, n = v.shape
    cols = np.zeros((nsamp, n, n, 4))
    idx = np.arange(n)
    sgn = coulomb_shape(v, smoothing_velocity)
    if kind == "standard":
        a = np.atleast_2d(np.asarray(a, float))
        cols[:, idx, idx] = np.stack([sgn, v, a, np.ones_like(v)], -1)
    elif kind == "momentum":
        cols[:, idx, idx, 2] = v
    elif kind == "rate":
        cols[:, idx, idx] = -np.stack([sgn, v, np.zeros_like(v), np.ones_like(v)], -1)
    else:
        raise ValueError(f"unknown friction regressor kind {kind!r}")
    return cols.reshape(nsamp, n, 4 * n)
