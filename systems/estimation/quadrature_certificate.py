"""A certificate for the quadrature of ∫W_c θ dt that needs no assumption on the integrand (A5),
only a bound on the joint accelerations between the samples (docs/guarantees.md §5, "A5
certified from an acceleration bound").

On a step [t_k, t_k+1] of length h with |q̈_j| ≤ A_j there, the measured (exact, A3) samples
(q_k, q̇_k), (q_k+1, q̇_k+1) confine the motion to a box per sub-interval of the step
(`step_boxes`); an interval enclosure of W_c over each box (`interval_rate_regressor`, the
interval twin of segments.rate_regressor_samples + the friction rate columns) then bounds
∫f − quadrature(f) for f = W_c θ and every θ in the parameter box (`certified_step_bounds`):
    ∫ f dt = Σ_i ∫_{sub-interval i} f dt ∈ (h/m) Σ_i [W](box_i) θ,   quadrature = h W̄ θ,
so |error| ≤ (h/m)·mag((Σ_i [W](box_i) − m W̄)·[θ]), W̄ = (W_k + W_k+1)/2 (trapezoid) or W_k
(left sum). For a tight box this is (1/m) of h·|Δf|/2, the error of a monotone step, hence
comparable with A5's ¼κh²·max(a) while resting on the acceleration bound only.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from safesysid.systems.math.intervals import Interval, _down, _up, dot_rounding
from safesysid.systems.model import regressors

from .segments import SegmentRows, _pair_factors, integrand_rates, neighbour_max, rate_regressor_samples
from .settings import EstimatorSettings

if TYPE_CHECKING:
    from safesysid.systems.model.robot_model import RobotModel


def step_boxes(
    t: np.ndarray, q: np.ndarray, v: np.ndarray, accel: np.ndarray, substeps: int
) -> tuple[Interval, Interval, np.ndarray]:
    """Boxes (q, v) (N − 1, m, n) holding the motion on each of m equal sub-intervals of every
    step, given |q̈| ≤ accel (N − 1, n) on the step, and (N − 1,) bool: the samples contradict
    the bound (|Δq̇| > A h on some joint; the boxes are then not valid).

    v: from both ends, v(s) ≥ lower(s) = max(v_k − A s, v_k+1 − A(h − s)) (convex) and v(s) ≤
    upper(s) = min(v_k + A s, v_k+1 + A(h − s)) (concave); on [s_i, s_i+1] the box is
    [lower(clip(s*)), upper(clip(s**))], s*, s** where the two lines meet. q: q_k + ∫_0^s v with
    ∫_0^{s_i} v in s_i·(hull of the boxes before) and ∫_{s_i}^s v in [0, h/m]·box_i, intersected
    with the same from q_k+1 backwards."""
    h = np.diff(t)[:, None, None]  # (N-1, 1, 1)
    a = np.asarray(accel, float)[:, None, :]
    v0, v1, q0, q1 = v[:-1, None], v[1:, None], q[:-1, None], q[1:, None]
    contradicted = np.any(np.abs(v[1:] - v[:-1]) > _up(accel * np.diff(t)[:, None]), 1)
    edges = h * (np.arange(substeps + 1) / substeps)[None, :, None]  # (N-1, m+1, 1)
    s_lo, s_hi = edges[:, :-1], edges[:, 1:]
    safe_a = np.maximum(a, 1e-300)
    s_low = np.clip((v0 - v1 + a * h) / (2 * safe_a), s_lo, s_hi)
    s_up = np.clip((v1 - v0 + a * h) / (2 * safe_a), s_lo, s_hi)
    v_lo = _down(np.maximum(v0 - a * s_low, v1 - a * (h - s_low)) - _pad(v0, v1, a, h))
    v_hi = _up(np.minimum(v0 + a * s_up, v1 + a * (h - s_up)) + _pad(v0, v1, a, h))
    v_hi = np.maximum(v_hi, v_lo)  # empty only when the bound is contradicted (flagged)
    # hulls of the v boxes before sub-interval i (on [0, s_i]) and after it (on [s_i+1, h])
    lo_acc, hi_acc = np.minimum.accumulate(v_lo, 1), np.maximum.accumulate(v_hi, 1)
    prev_lo = np.concatenate([lo_acc[:, :1], lo_acc[:, :-1]], 1)
    prev_hi = np.concatenate([hi_acc[:, :1], hi_acc[:, :-1]], 1)
    lo_rev = np.minimum.accumulate(v_lo[:, ::-1], 1)[:, ::-1]
    hi_rev = np.maximum.accumulate(v_hi[:, ::-1], 1)[:, ::-1]
    next_lo = np.concatenate([lo_rev[:, 1:], lo_rev[:, -1:]], 1)
    next_hi = np.concatenate([hi_rev[:, 1:], hi_rev[:, -1:]], 1)
    sub = h / substeps
    step_lo, step_hi = np.minimum(0.0, sub * v_lo), np.maximum(0.0, sub * v_hi)  # ∫ over part of box i
    before, after = s_lo, h - s_hi
    fwd_lo, fwd_hi = q0 + before * prev_lo + step_lo, q0 + before * prev_hi + step_hi
    bwd_lo, bwd_hi = q1 - after * next_hi - step_hi, q1 - after * next_lo - step_lo
    mags = np.maximum(np.abs(prev_lo), np.abs(prev_hi)) + np.maximum(np.abs(next_lo), np.abs(next_hi))
    pad = dot_rounding(3) * (np.abs(q0) + np.abs(q1) + h * mags + sub * (np.abs(v_lo) + np.abs(v_hi)))
    q_lo, q_hi = _down(np.maximum(fwd_lo, bwd_lo) - pad), _up(np.minimum(fwd_hi, bwd_hi) + pad)
    q_hi = np.maximum(q_hi, q_lo)
    return Interval(q_lo, q_hi), Interval(v_lo, v_hi), contradicted


def _pad(v0, v1, a, h):
    """Rounding of the few float operations of the v bounds (each within eps of its operands)."""
    return dot_rounding(4) * (np.abs(v0) + np.abs(v1) + 2 * a * h)


def _stack(items, axis=-1):
    return Interval(np.stack([x.lo for x in items], axis), np.stack([x.hi for x in items], axis))


def _cross(a, b):
    """Interval cross product over the last axis (3)."""
    nx, pv = [1, 2, 0], [2, 0, 1]
    return a[..., nx] * b[..., pv] - a[..., pv] * b[..., nx]


def _cross_motion(v, m):
    w, u = v[..., :3], v[..., 3:]
    return _stack_cat([_cross(w, m[..., :3]), _cross(w, m[..., 3:]) + _cross(u, m[..., :3])])


def _stack_cat(items):
    return Interval(np.concatenate([x.lo for x in items], -1), np.concatenate([x.hi for x in items], -1))


def _times_const(x: Interval, c: np.ndarray) -> Interval:
    """Interval (..., a, k) times a point matrix (k, b): exact hull of a linear map, outward."""
    c = np.asarray(c, float)
    mid = x.mid @ c
    rad = x.rad @ np.abs(c)
    err = dot_rounding(c.shape[0]) * (x.mag @ np.abs(c))
    return Interval(_down(mid - rad - err), _up(mid + rad + err))


def _transpose_times(r: Interval, x: Interval) -> Interval:
    """Rᵀ x for interval rotations (..., 3, 3) and vectors (..., 3)."""
    return (r * x[..., :, None]).sum(-2)


def _to_body(r: Interval, p: Interval, x: Interval) -> Interval:
    """World motion vectors (..., 6) about the origin to body coordinates at (R, p)."""
    w, u = x[..., :3], x[..., 3:]
    return _stack_cat([_transpose_times(r, w), _transpose_times(r, u + _cross(w, p))])


def _kinematics(tree, q: Interval, v: Interval):
    """Interval world poses R (M, n, 3, 3), p, screws S, twists V and screw rates Ṡ (M, n, 6):
    regressors.forward_kinematics on boxes, operation by operation."""
    from safesysid.systems.math import intervals

    cos, sin = intervals.cos(q), intervals.sin(q)
    R, p, S, V, Sd = [], [], [], [], []
    for i in range(tree.n):
        par = tree.parent[i]
        xpj, xjc = tree.X_parent_joint[i], tree.X_joint_child[i]
        a = regressors._z_to(tree.axis[i])
        if par < 0:
            m = len(q)
            r_f = Interval(np.broadcast_to(xpj[:3, :3] @ a, (m, 3, 3)))
            p_f = Interval(np.broadcast_to(xpj[:3, 3], (m, 3)))
        else:
            r_f = _times_const(R[par], xpj[:3, :3] @ a)
            p_f = p[par] + _times_const(R[par], xpj[:3, 3:4])[..., 0]
        z = r_f[:, :, 2]
        if tree.prismatic[i]:
            raise NotImplementedError("the quadrature certificate covers revolute joints only")
        c, s_ = cos[:, i, None], sin[:, i, None]
        r_m = _stack([r_f[:, :, 0] * c + r_f[:, :, 1] * s_, r_f[:, :, 1] * c - r_f[:, :, 0] * s_, z], -1)
        S.append(_stack_cat([z, _cross(p_f, z)]))
        R.append(_times_const(r_m, a.T @ xjc[:3, :3]))
        p.append(p_f + _times_const(r_m, (a.T @ xjc[:3, 3])[:, None])[..., 0])
        own = S[i] * v[:, i, None]
        if par < 0:
            Sd.append(Interval(np.zeros((len(q), 6))))
            V.append(own)
        else:
            Sd.append(_cross_motion(V[par], S[i]))
            V.append(V[par] + own)
    return R, p, S, V, Sd


_K = np.stack([regressors.inertia_times(np.eye(6)[b]) for b in range(6)], 1).reshape(36, 10)  # [a·6 + b]


def interval_rate_regressor(robot: RobotModel, q: Interval, v: Interval) -> Interval:
    """Interval W_c (M, n, 14 n) holding segments.rate_regressor_samples + the friction "rate"
    columns for every state in the boxes q, v (M, n): the rigid block of body i and ancestor
    joint j is sᵀK(x) with (s, x) = (Ṡ_j, V_i) and (S_j, −A_g), all in body i's coordinates."""
    tree, n = robot.tree, robot.n
    R, p, S, V, Sd = _kinematics(tree, q, v)
    anc = tree.ancestors()
    m = len(q)
    lo, hi = np.zeros((m, n, 14 * n)), np.zeros((m, n, 14 * n))
    grav = np.concatenate([np.zeros(3), np.asarray(tree.gravity, float)])
    for i in range(n):  # all ancestor joints of body i at once: (M, k, 6)
        js = np.flatnonzero(anc[:, i])
        r, pos = R[i][:, None], p[i][:, None]
        vb = _to_body(R[i], p[i], V[i])[:, None, None, :]
        gb = _to_body(R[i], p[i], Interval(np.broadcast_to(grav, (m, 6))))[:, None, None, :]
        sd = _to_body(r, pos, _stack([Sd[j] for j in js], 1))[..., :, None]
        s = _to_body(r, pos, _stack([S[j] for j in js], 1))[..., :, None]
        outer = sd * vb + s * gb  # (M, k, 6, 6): [a, b] = s_a x_b
        k = len(js)
        block = _times_const(Interval(outer.lo.reshape(m, k, 36), outer.hi.reshape(m, k, 36)), _K)
        lo[:, js, 10 * i : 10 * i + 10], hi[:, js, 10 * i : 10 * i + 10] = block.lo, block.hi
    sgn = _coulomb(v, robot.coulomb_smoothing)
    for j in range(n):  # rate columns [Fc, Fv, Ia, beta] = −(sgn v, v, 0, 1)
        base = 10 * n + 4 * j
        lo[:, j, base], hi[:, j, base] = -sgn.hi[:, j], -sgn.lo[:, j]
        lo[:, j, base + 1], hi[:, j, base + 1] = -v.hi[:, j], -v.lo[:, j]
        lo[:, j, base + 3], hi[:, j, base + 3] = -1.0, -1.0
    return Interval(lo, hi)


def _coulomb(v: Interval, smoothing: float) -> Interval:
    """regressors.coulomb_shape over boxes (monotone in v), outward."""
    if smoothing > 0:
        return Interval(
            np.maximum(_down(np.tanh(v.lo / smoothing)) - 1e-15, -1.0),
            np.minimum(_up(np.tanh(v.hi / smoothing)) + 1e-15, 1.0),
        )
    return Interval(np.sign(v.lo), np.sign(v.hi))


def point_rate_regressor(robot: RobotModel, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """W_c (N, n, 14 n) at the samples, as the rows use it (rigid + friction rate columns)."""
    fric = regressors.friction_columns(v, kind="rate", smoothing_velocity=robot.coulomb_smoothing)
    return np.concatenate([rate_regressor_samples(_pair_factors(robot.tree, q, v), robot.n), fric], -1)


def certified_step_bounds(
    robot: RobotModel,
    t: np.ndarray,
    q: np.ndarray,
    v: np.ndarray,
    accel: np.ndarray,
    theta_box: tuple[np.ndarray, np.ndarray],
    *,
    integration: str,
    substeps: int = 4,
) -> tuple[np.ndarray, np.ndarray]:
    """Per step and joint (N − 1, n), a bound on |∫ f dt − quadrature(f)| over the step for
    f = W_c θ and every θ in theta_box = (centre, radius), given |q̈| ≤ accel (N − 1, n) on the
    step; and (N − 1,) bool, the steps whose samples contradict the bound (their value is inf).

    ∫ f ∈ (h/m) Σ_i [W](box_i)·θ (m = substeps boxes, `step_boxes`) and the quadrature is h W̄ θ,
    so the error lies in (h/m)·[D]·[θ], D = Σ_i [W](box_i) − m W̄ (module docstring)."""
    n = robot.n
    qb, vb, contradicted = step_boxes(t, q, v, accel, substeps)
    steps = len(t) - 1
    flat = lambda x: Interval(x.lo.reshape(-1, n), x.hi.reshape(-1, n))  # noqa: E731
    w_box = interval_rate_regressor(robot, flat(qb), flat(vb))
    w_sum = _sum_substeps(w_box, steps, substeps)
    w_pts = point_rate_regressor(robot, q, v)
    w_bar = w_pts[:-1] if integration == "euler" else 0.5 * (w_pts[:-1] + w_pts[1:])
    d = w_sum - substeps * w_bar
    centre, radius = (np.asarray(x, float) for x in theta_box)
    mid = d.mid @ centre
    spread = d.rad @ np.abs(centre) + d.mag @ radius
    err = dot_rounding(2 * d.shape[-1] + substeps) * (
        d.mag @ (np.abs(centre) + radius) + substeps * np.abs(w_bar) @ np.abs(centre)
    )
    h = np.diff(t)[:, None]
    bound = _up(h / substeps * _up(np.abs(mid) + spread + err) * (1 + dot_rounding(2)))
    bound[contradicted] = np.inf
    return bound, contradicted


def _sum_substeps(w: Interval, steps: int, substeps: int) -> Interval:
    lo = w.lo.reshape((steps, substeps) + w.shape[1:])
    hi = w.hi.reshape((steps, substeps) + w.shape[1:])
    return Interval(lo, hi).sum(1)


def certify_rows(
    rows: SegmentRows,
    robot: RobotModel,
    samples: tuple[np.ndarray, np.ndarray, np.ndarray],
    bounds: np.ndarray,
    settings: EstimatorSettings,
    *,
    theta_box: tuple[np.ndarray, np.ndarray],
    accel: np.ndarray,
    exceeded: np.ndarray | None = None,
) -> SegmentRows:
    """The rows of `bounds` (built by segments.build_segment_rows on samples = (t, q, v)) with
    each segment's quadrature term Σ_steps max(A5's bound, `certified_step_bounds`), valid with
    A5 or without it given |q̈| ≤ accel between the samples ((n,), or per step of the samples'
    range bounds[0, 0]..bounds[-1, 1]: (steps, n); inf: no bound on that step), and never below
    the samples' own term (equal to it where A5's bound dominates on every step: a5_shown; the
    increase is added, so a continuous torque's own term stays). A step whose samples contradict
    the bound, or whose known motion exceeds it (exceeded, (steps,) bool), certifies nothing: its
    segment keeps A5's term, accel_violated; a segment with an unbounded step keeps A5's term."""
    lo, hi = int(bounds[:, 0].min()), int(bounds[:, 1].max())
    tt, qq, vv = (x[lo : hi + 1] for x in samples)
    loc = bounds - lo
    steps = len(tt) - 1
    accel = np.broadcast_to(np.asarray(accel, float), (steps, robot.n))
    open_ = ~np.all(np.isfinite(accel), 1)
    finite = np.where(open_[:, None], 0.0, accel)
    cert, contradicted = certified_step_bounds(robot, tt, qq, vv, finite, theta_box, integration=settings.integration)
    contradicted = (contradicted & ~open_) | (False if exceeded is None else exceeded)
    fric = regressors.friction_columns(vv, kind="rate", smoothing_velocity=robot.coulomb_smoothing)
    rates = integrand_rates(tt, _pair_factors(robot.tree, qq, vv), fric, *theta_box)
    c = 0.5 if settings.integration == "euler" else 0.25
    h2 = np.diff(tt) ** 2
    quad = rows.quad.copy()
    shown, bad, unbounded = (np.zeros(len(loc), bool) for _ in range(3))
    for s, (a, b) in enumerate(loc):
        a5 = c * settings.quadrature_safety * h2[a:b, None] * neighbour_max(rates[a:b])
        bad[s] = bool(contradicted[a:b].any())
        unbounded[s] = bool(open_[a:b].any())
        shown[s] = not (bad[s] or unbounded[s]) and bool(np.all(cert[a:b] <= a5))
        if not (
            shown[s] or bad[s] or unbounded[s]
        ):  # what the certificate adds over A5's term (a continuous torque's stays)
            both = np.maximum(a5, cert[a:b]).sum(0)
            quad[s] = np.maximum(both, quad[s] + np.maximum(0.0, both - a5.sum(0)))
    return replace(rows, quad=quad, a5_certified=~(bad | unbounded), a5_shown=shown, accel_violated=bad)
