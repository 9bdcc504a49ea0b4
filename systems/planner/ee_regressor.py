"""End-effector regressor W_e(q, qd, qdd) of the exciting cost (the planner's and the Fourier
excitation's), complex-step safe: all arithmetic analytic."""

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.math.spatial import cross, to_body
from safesysid.systems.model import regressors
from safesysid.systems.planner.interval_dynamics import signed_selection

# Own pass because regressors.forward_kinematics fills float buffers (the imaginary part would be
# lost). K(x) and x x* are regressors.py's, as exact gathers (signed_selection): any dtype,
# and no BLAS call (a threaded one on the shared cores costs ~10 ms here).
_K_MAP = signed_selection(regressors.inertia_times(np.eye(6)))
_FORCE_CROSS_MAP = signed_selection(regressors.cross_force_matrix(np.eye(6)))


def _linear(x, selection, shape):
    """The linear map of `selection` applied to x (..., 6) -> (..., *shape)."""
    comp, sign = selection
    return (x[..., comp] * sign).reshape(x.shape[:-1] + shape)


def _motion_cross(v, m):
    """regressors.cross_motion on spatial.cross (np.cross's overhead: ~3 ms per W_e call here)."""
    w, u = v[..., :3], v[..., 3:]
    return np.concatenate([cross(w, m[..., :3]), cross(w, m[..., 3:]) + cross(u, m[..., :3])], -1)


def ee_standard_regressor(
    tree: regressors.KinematicTree, body: int, q: ArrayLike, *, v: ArrayLike, a: ArrayLike
) -> np.ndarray:
    """W_e (N, n, 10): the end-effector (body `body`) columns of the standard regressor.

    Same as RobotModel.standard_regressor(q, v, a)[..., ee_slice]; dtype-generic (complex-step).
    """
    dtype = np.result_type(q, v, a, float)
    q, v, a = (np.atleast_2d(np.asarray(x)).astype(dtype) for x in (q, v, a))
    nsamp, n = q.shape
    R = [None] * n
    p = [None] * n
    S = np.zeros((nsamp, n, 6), dtype)
    V = [None] * n
    A = [None] * n
    g = np.concatenate([np.zeros(3), -tree.gravity])
    consts = _chain_constants(tree)
    for i in range(n):
        par = tree.parent[i]
        rpj, tpj, rjc, tjc = consts[i]
        if par < 0:
            r_f = np.broadcast_to(rpj, (nsamp, 3, 3)).astype(dtype)
            p_f = np.broadcast_to(tpj, (nsamp, 3)).astype(dtype)
            v_par = np.zeros((nsamp, 6), dtype)
            a_par = np.broadcast_to(g, (nsamp, 6)).astype(dtype)
        else:
            r_f = regressors._times_const(R[par], rpj)
            p_f = p[par] + R[par] @ tpj
            v_par, a_par = V[par], A[par]
        z = r_f[..., 2]  # the joint axis is the frame's z after the constant change of basis
        if tree.prismatic[i]:
            r_m, p_m = r_f, p_f + z * q[:, i, None]
            S[:, i] = np.concatenate([np.zeros_like(z), z], -1)
        else:
            s, c = np.sin(q[:, i])[:, None], np.cos(q[:, i])[:, None]
            x_, y_ = r_f[..., 0], r_f[..., 1]
            r_m, p_m = np.stack([c * x_ + s * y_, c * y_ - s * x_, z], -1), p_f  # r_f @ Rz(q)
            S[:, i] = np.concatenate([z, cross(p_f, z)], -1)
        R[i] = regressors._times_const(r_m, rjc)
        p[i] = p_m + r_m @ tjc
        V[i] = v_par + S[:, i] * v[:, i, None]
        A[i] = a_par + S[:, i] * a[:, i, None] + _motion_cross(v_par, S[:, i]) * v[:, i, None]
    e = body
    vb = to_body(R[e], p[e], V[e])
    ab = to_body(R[e], p[e], A[e])
    anc = np.flatnonzero(tree.ancestors()[:, e])
    sb = to_body(R[e][:, None], p[e][:, None], S[:, anc])  # (N, k, 6) screws in the body frame
    y = _linear(ab, _K_MAP, (6, 10)) + _linear(vb, _FORCE_CROSS_MAP, (6, 6)) @ _linear(
        vb, _K_MAP, (6, 10)
    )  # I a + v x* I v
    out = np.zeros((nsamp, n, 10), dtype)
    out[:, anc] = sb @ y
    return out


_CHAIN = {}


def _chain_constants(tree):
    """Per joint (R_pj P, t_pj, P^T R_jc, P^T t_jc) with P a rotation taking z to the joint axis,
    so the joint rotation is a rotation about z (column arithmetic instead of a 3x3 product)."""
    key = id(tree)
    if key not in _CHAIN or _CHAIN[key][0] is not tree:
        out = []
        for i in range(tree.n):
            axis = np.asarray(tree.axis[i], float)
            rot = regressors._z_to(axis / np.linalg.norm(axis))  # columns x, y, z = axis
            xpj, xjc = tree.X_parent_joint[i], tree.X_joint_child[i]
            out.append((xpj[:3, :3] @ rot, xpj[:3, 3].copy(), rot.T @ xjc[:3, :3], rot.T @ xjc[:3, 3]))
        _CHAIN[key] = (tree, out)
    return _CHAIN[key][1]
