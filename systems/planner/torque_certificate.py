"""The torque bounds of the planner's certificate (interval_dynamics.py's docstring): sup |u_j| of
the ARMOUR law's input over a state box from the interval or affine passivity regressor, the
robust term ||w_bar|| + the barrier excess, and `robust_bound_vertex`'s tighter w_bar."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.controller.armour import TrackingBounds, robust_gain_bound
from safesysid.systems.math.intervals import Interval, _up, dot_rounding
from safesysid.systems.planner.affine_forms import Affine
from safesysid.systems.planner.interval_dynamics import interval_mass_spread, interval_passivity_regressor, merge_rows

if TYPE_CHECKING:
    from safesysid.systems.model.robot_model import RobotModel


def robust_bound_vertex(
    robot: RobotModel,
    q: Interval,
    v: Interval,
    va: Interval,
    aa: Interval,
    theta0: ArrayLike,
    theta_lo: ArrayLike,
    theta_hi: ArrayLike,
    block: slice | np.ndarray,
    *,
    full: Interval | None = None,
    b_rows: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Tighter w_bar (N, n) for the parameters in `block` (e.g. the end effector's 10).

    W_p is affine in aa: W_p = A(q, v, va) + sum_j B_j(q) aa_j (B_j: the M(q) columns, no gravity,
    no velocity). sum_k |W_p,ik| d_k is convex in aa, so its max over the aa box is at a vertex;
    with interval A, B_j over the rest of the box, the max over the 2^n aa vertices of
    sum_k d_k mag(A_ik + sum_j B_j,ik aa_j) bounds it. Parameters outside `block` use the plain
    sum_k mag(W_p,ik) d_k. B_j depends on q only: it is evaluated on hulls of `b_rows`
    consecutive q boxes (cheap, q moves little). Returns (w_bar (N, n), plain w_bar (N, n)).
    """
    n = robot.n
    nb = q.shape[0]
    theta0 = np.asarray(theta0, float)
    d = np.maximum(np.maximum(np.asarray(theta_hi, float) - theta0, theta0 - np.asarray(theta_lo, float)), 0.0)
    a_part = interval_passivity_regressor(robot, q, v, va, Interval(np.zeros((nb, n))))
    # B_j: unit aa_j, no gravity, no velocity, on the q hulls; batched over j.
    q_hull = merge_rows(q, b_rows)
    ng = q_hull.shape[0]
    zeros = Interval(np.zeros((n * ng, n)))
    b_all = interval_passivity_regressor(
        robot,
        Interval(np.tile(q_hull.lo, (n, 1)), np.tile(q_hull.hi, (n, 1))),
        zeros,
        zeros,
        Interval(np.repeat(np.eye(n), ng, axis=0)),
        gravity=False,
    )
    cols = np.zeros(a_part.lo.shape[-1], bool)
    cols[block] = True
    fr = 10 * n + 4 * np.arange(n)
    cols[fr] = cols[fr + 1] = cols[fr + 2] = cols[fr + 3] = False  # friction: bounded plainly
    owner = np.arange(nb) // b_rows
    a_lo, a_hi = a_part.lo[..., cols], a_part.hi[..., cols]  # (N, n, p)
    b_lo = b_all.lo[..., cols].reshape(n, ng, n, -1)[:, owner]  # (j, N, n, p)
    b_hi = b_all.hi[..., cols].reshape(n, ng, n, -1)[:, owner]
    # Every vertex at once: the sums over j for all 2^n choices of aa_j in {lo, hi}, by doubling.
    lo, hi = a_lo[None], a_hi[None]
    scale = np.maximum(np.abs(a_lo), np.abs(a_hi))
    for j in range(n):
        opts_lo, opts_hi = [], []
        for x in (aa.lo[:, j], aa.hi[:, j]):
            p1, p2 = b_lo[j] * x[:, None, None], b_hi[j] * x[:, None, None]
            opts_lo.append(np.minimum(p1, p2))
            opts_hi.append(np.maximum(p1, p2))
        lo = np.concatenate([lo + opts_lo[0], lo + opts_lo[1]])
        hi = np.concatenate([hi + opts_hi[0], hi + opts_hi[1]])
        scale = scale + np.maximum(
            np.maximum(np.abs(b_lo[j]), np.abs(b_hi[j]))
            * np.maximum(np.abs(aa.lo[:, j]), np.abs(aa.hi[:, j]))[:, None, None],
            0,
        )
    err = 4 * dot_rounding(n) * scale  # rounding of the sums above (lo and hi, each of n products)
    mag = np.maximum(np.abs(lo), np.abs(hi)) + err[None]
    best = _up((mag @ d[cols]).max(0) * (1 + dot_rounding(int(cols.sum()))))
    full = interval_passivity_regressor(robot, q, v, va, aa) if full is None else full
    rest = full.mag[..., ~cols] @ d[~cols]
    plain = full.mag @ d
    return _up(np.minimum(plain, best + rest)), plain


def barrier_excess(
    robot: RobotModel, q: Interval, theta_lo: ArrayLike, theta_hi: ArrayLike, bounds: TrackingBounds, *, rows: int = 1
) -> np.ndarray:
    """(N, n): alpha eps mu_j / 2 over each configuration box, the amount by which the controller's
    |v_j| = lambda |r_j|/|r| may exceed |w_bar| on the tube (controller.robust_gain_bound with the
    per-joint mu_j of `joint_spread_bound`); mu on hulls of `rows` consecutive boxes (it varies
    slowly; fewer, slightly larger boxes)."""
    if bounds.eps == 0 or bounds.alpha == 0:
        return np.zeros(q.shape)
    mu = interval_mass_spread(robot, merge_rows(q, rows), theta_lo, theta_hi, per_joint=True)
    mu = mu[np.arange(q.shape[0]) // rows]
    return robust_gain_bound(np.zeros_like(mu), bounds.alpha, bounds.eps, mu=mu)


def torque_bound(
    wp: Interval, theta0: ArrayLike, theta_lo: ArrayLike, *, theta_hi: ArrayLike, excess: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """sup |u| per (interval, joint) over the boxes of wp (Interval (N, n, p)).

    u = W_p theta0 + v, |v_j| <= ||w_bar||_2 + excess_j (excess (N, n) from barrier_excess on the
    same boxes), w_bar_i <= sum_k |W_p,ik| d_k with d = max(theta_hi - theta0, theta0 - theta_lo).
    Returns (sup|u| (N, n), nominal part (N, n), robust part (N, n)).
    """
    theta0 = np.asarray(theta0, float)
    d = np.maximum(np.asarray(theta_hi, float) - theta0, theta0 - np.asarray(theta_lo, float))
    d = np.maximum(d, 0.0)
    mid = wp.mid @ theta0
    rad = wp.rad @ np.abs(theta0)
    err = dot_rounding(len(theta0)) * (wp.mag @ np.abs(theta0))  # the mid-radius products over theta
    nominal = _up(np.abs(mid) + rad + err)
    wbar = _up((wp.mag @ d) * (1 + 1e-12))
    robust = robust_term(wbar, excess)
    return _up(nominal + robust), nominal, robust


def affine_torque_bound(
    wp: Affine, theta0: ArrayLike, theta_lo: ArrayLike, *, theta_hi: ArrayLike, excess: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """torque_bound for an affine regressor (affine_passivity_regressor): the nominal torque keeps the
    dependence across columns, |c theta0 + (g theta0) . s| <= |c theta0| + B(g theta0) + r |theta0|,
    and w_bar_i <= sum_k d_k (|c_ik| + B(g_ik) + r_ik) (each entry's own range, B of affine_forms)."""
    theta0 = np.asarray(theta0, float)
    d = np.maximum(np.maximum(np.asarray(theta_hi, float) - theta0, theta0 - np.asarray(theta_lo, float)), 0.0)
    k = len(theta0)
    centre = wp.c @ theta0
    gen = np.einsum("...ks,k->...s", wp.g, theta0)
    err = dot_rounding(k) * (wp.mag @ np.abs(theta0))  # the sums over k above
    nominal = _up(np.abs(centre) + wp.spread(gen) + wp.r @ np.abs(theta0) + err)
    # Entries whose sign is fixed on the whole set (|c| >= spread + r) add linearly:
    # sum_k d_k |x_k| = sum_k d_k sgn(c_k) x_k there, so their generators may cancel across k.
    spread = wp.spread()
    fixed = np.abs(wp.c) >= (spread + wp.r) * (1 + 1e-12)
    sd = np.where(fixed, np.sign(wp.c), 0.0) * d
    linear = np.where(fixed, np.abs(wp.c) + wp.r, 0.0) @ d + wp.spread(np.einsum("...ks,...k->...s", wp.g, sd))
    free = np.where(fixed, 0.0, np.abs(wp.c) + spread + wp.r) @ d
    wbar = _up((linear + free + err) * (1 + 1e-12))
    robust = robust_term(wbar, excess)
    return _up(nominal + robust), nominal, robust


def robust_term(w_bar: np.ndarray, excess: np.ndarray) -> np.ndarray:
    """(N, n): rounded-up ||w_bar||_2 (last axis) + excess (N, n): the bound of the controller's |v_j|."""
    return _up(_up(np.linalg.norm(w_bar, axis=-1) * (1 + 1e-12))[:, None] + excess)
