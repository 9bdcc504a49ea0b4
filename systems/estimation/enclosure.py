"""The interval of θ_e (Theorem 2, exact hull of the linear map): the left inverses, the error
terms of the box, the certified set-membership LP and the LMI test of a box.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from safesysid.systems.math.intervals import dot_rounding
from safesysid.systems.model import inertial
from scipy.optimize import linprog  # imported here: its first import costs ~0.3 s

from .log_cholesky import ls_cost_terms
from .segments import SegmentRows
from .settings import EPS, EstimatorSettings


def _pinv(Y2):
    """Y⁺ = R⁻¹Qᵀ (QR, better conditioned than the normal equations) and cond(Y)."""
    Q, R = np.linalg.qr(Y2)
    sv = np.linalg.svd(R, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    if not np.isfinite(cond):
        return None, cond
    return np.linalg.solve(R, Q.T), cond


def torque_row_radius(rows: SegmentRows) -> np.ndarray:
    """(S, n) declared bound of the torque part of each row, Σ_k w_k r_k."""
    return rows.w_first[:, None] * rows.r_first + rows.w_last[:, None] * rows.r_last + rows.r_inner


def row_bounds(rows: SegmentRows, rad_r: np.ndarray) -> np.ndarray:
    """Declared error bound of each row of U (torque + θ_r + quadrature), (S n,); rad_r the
    half-widths of [θ_r]."""
    r_thr = np.abs(rows.D_r) @ rad_r
    return (torque_row_radius(rows) + r_thr + rows.quad).ravel()


def _left_inverse(rows: SegmentRows, theta_r, rad_r, settings):
    """A left inverse L of Y (L Y = I) and the NLP's quadratic (A, b, c) with
    ‖·‖² = θᵀAθ − 2bᵀθ + c, for the chosen point estimate:

    "map":   θ_r is marginalised with its box as prior (δθ_r ~ rad/√3 per entry) and rows are
             whitened by their noise scale (σ_row² = Σ_k w_k² r_k²/3 for independent uniform
             torque errors): the cost is ‖M^½ W (Y θ_e − U)‖², M = I − D̃(D̃ᵀD̃ + Λ)⁻¹D̃ᵀ. It is
             the paper's ‖Y P(η) − U‖² on whitened data, and removes most of the bias a wrong
             θ_r puts on θ0 (the mass error drops ~2x in the tests).
    "paper": rows scaled by 1/(declared row bound) ("bound") or unscaled ("none").
    The interval does not depend on this choice being right: any left inverse gives an enclosure.
    """
    S, n = rows.T.shape
    Y2 = rows.Y.reshape(S * n, 10)
    Dr2 = rows.D_r.reshape(S * n, -1)
    U = -Dr2 @ theta_r + rows.T.ravel()
    if settings.point_estimate == "map":
        sig = (
            np.sqrt(
                (
                    rows.w_first[:, None] ** 2 * rows.r_first**2
                    + rows.w_last[:, None] ** 2 * rows.r_last**2
                    + rows.r_inner_sq
                )
                / 3.0
            ).ravel()
            + rows.quad.ravel()
        )
        wrow = 1.0 / np.maximum(sig, 1e-12 * max(sig.max(), 1e-300))
        keep = (rad_r > 0) & (np.abs(Dr2).max(0) > 0)
        Yt, Dt, Ut = Y2 * wrow[:, None], Dr2[:, keep] * wrow[:, None], U * wrow
        K = Dt.T @ Dt + np.diag(3.0 / rad_r[keep] ** 2)
        Z = np.linalg.solve(K, Dt.T)  # (k, R)
        YtM = Yt.T - (Yt.T @ Dt) @ Z
        A = YtM @ Yt
        A = 0.5 * (A + A.T)
        b = YtM @ Ut
        DU = Dt.T @ Ut
        c = float(Ut @ Ut - DU @ np.linalg.solve(K, DU))
        try:
            L = np.linalg.solve(A, YtM) * wrow
        except np.linalg.LinAlgError:
            return None
        return L, A, b, c, U
    if settings.row_weighting == "bound":
        bnd = row_bounds(rows, rad_r)
        wrow = 1.0 / np.maximum(bnd, 1e-12 * max(bnd.max(), 1e-300))
    else:
        wrow = np.ones(S * n)
    pinv_w, _ = _pinv(Y2 * wrow[:, None])
    if pinv_w is None:
        return None
    A, b, c = ls_cost_terms(Y2 * wrow[:, None], U * wrow)
    return pinv_w * wrow, A, b, c, U


def interval_hull(
    rows: SegmentRows, theta_r: np.ndarray, rad_r: np.ndarray, *, settings: EstimatorSettings
) -> tuple[dict | None, float]:
    """Centre L U(m) and radii of the exact hull {L(U(m') − e) : m' ∈ [m], |e| ≤ quad}.

    L is a left inverse of Y (`_left_inverse`): θ_e = L(U(m_true) − e) exactly, so the box
    encloses the truth; θ* = L U(m) is the estimate of Theorem 2 when the LMI is inactive and
    L ∂U/∂m its constant Jacobian, so the box is also the exact hull of θ*([m]).
    """
    S, n = rows.T.shape
    Y2 = rows.Y.reshape(S * n, 10)
    Dr2 = rows.D_r.reshape(S * n, -1)
    _, cond = _pinv(Y2)  # cond of the raw Y (the paper's figure)
    inv = None if not np.isfinite(cond) else _left_inverse(rows, theta_r, rad_r, settings)
    if inv is None:
        return None, cond
    L, A, b, c, U = inv
    centre = L @ U
    G = L.reshape(10, S, n)
    # Torque samples: each sample appears in one segment, or in two when it is a shared boundary.
    first = G * rows.w_first[None, :, None]
    prev_last = np.zeros_like(G)
    prev_last[:, 1:] = G[:, :-1] * rows.w_last[None, :-1, None]
    first = first + prev_last * rows.shared_prev[None, :, None]
    next_shared = np.zeros(S, bool)
    next_shared[:-1] = rows.shared_prev[1:]
    last = G * (rows.w_last * ~next_shared)[None, :, None]
    rad_tau = (
        (np.abs(first) * rows.r_first).sum((1, 2))
        + (np.abs(last) * rows.r_last).sum((1, 2))
        + (np.abs(G) * rows.r_inner).sum((1, 2))
    )
    rad_theta_r = np.abs(L @ Dr2) @ rad_r
    rad_quad = np.abs(L) @ rows.quad.ravel()
    total = rad_tau + rad_theta_r + rad_quad
    # Float rounding: the computed L is a left inverse only up to E = L Y − I, so
    # θ_e = L(U − e) − E θ_e; bound |E θ_e| by |E|(|centre| + total) (E itself padded for its
    # own rounding), plus a relative pad for the rounding of L U and of the |·| sums.
    E = L @ Y2 - np.eye(10)
    E_abs = np.abs(E) + 4 * EPS * (S * n) * (np.abs(L) @ np.abs(Y2))
    rad_round = E_abs @ (np.abs(centre) + total)
    rad_round = rad_round + 64 * EPS * (S * n + Dr2.shape[1]) * (total + np.abs(L) @ np.abs(U)) + 1e-300
    return dict(
        centre=centre,
        rad_torque=rad_tau,
        rad_theta_r=rad_theta_r,
        rad_quad=rad_quad,
        rad_round=rad_round,
        U=U,
        A=A,
        b=b,
        c=c,
        pinv=L,
    ), cond


def set_membership_bounds(
    rows: SegmentRows,
    theta_r: np.ndarray,
    rad_r: np.ndarray,
    *,
    settings: EstimatorSettings,
    box_lo: np.ndarray,
    box_hi: np.ndarray,
    params: Iterable[int],
    previous: tuple | None = None,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Certified [min, max] of θ_e[i] (i in params) over the feasible polytope, by LP.
    previous: the last consistent data box, for settings.set_membership_window_s (set_membership_window).

    Variables x = (θ_e, θ_r); rows |Y θ_e + D_r θ_r − ∫τ| ≤ Σ_k w_k r_k + quadrature term (a
    boundary sample shared by two segments is let vary independently in each: a relaxation,
    so still an enclosure); θ_r in its box; θ_e in the Theorem-2 box (already proven).
    Each bound is certified by weak duality (`certified_lp_min`). Returns (lo, hi, feasible);
    lo/hi are NaN where not refined.
    """
    window_s = settings.set_membership_window_s
    rows, box_lo, box_hi = set_membership_window(rows, box_lo, box_hi, window_s=window_s, previous=previous)
    S, n = rows.T.shape
    Y2 = rows.Y.reshape(S * n, 10)
    Dr2 = rows.D_r.reshape(S * n, -1)
    # Order reduction of the θ_r zonotope: the lp_generators entries with the largest effect
    # stay LP variables; the others are fixed at nominal and their worst case |D_r,c| rad_c is
    # added to each row's bound (a relaxation, so still an enclosure; ~no loss at 40 of 88).
    effect = (np.abs(Dr2) * rad_r).sum(0)
    keep = np.zeros(len(theta_r), bool)
    keep[np.argsort(-effect)[: settings.lp_generators]] = True
    keep &= effect > 0
    fixed = Dr2[:, ~keep] @ theta_r[~keep]
    dropped = (np.abs(Dr2[:, ~keep]) * rad_r[~keep]).sum(1)
    A = np.hstack([Y2, Dr2[:, keep]])
    R = ((torque_row_radius(rows) + rows.quad).ravel() + dropped) * (1 + 1e-9)
    T = rows.T.ravel() - fixed
    A_ub = np.vstack([A, -A])
    b_ub = np.concatenate([T + R, R - T])
    lo_x = np.concatenate([box_lo, (theta_r - rad_r)[keep]])
    hi_x = np.concatenate([box_hi, (theta_r + rad_r)[keep]])
    out_lo, out_hi = np.full(10, np.nan), np.full(10, np.nan)
    for i in params:
        for sign in (1.0, -1.0):
            c = np.zeros(A.shape[1])
            c[i] = sign
            status, bound = certified_lp_min(c, A_ub, b_ub, lo_x, hi_x)
            if status == "infeasible":  # the data contradict the declared bounds
                return out_lo, out_hi, False
            if status != "ok":
                continue
            if sign > 0:
                out_lo[i] = bound
            else:
                out_hi[i] = -bound
    return out_lo, out_hi, True


def set_membership_window(
    rows: SegmentRows, lo: np.ndarray, hi: np.ndarray, *, window_s: float, previous: tuple | None
) -> tuple[SegmentRows, np.ndarray, np.ndarray]:
    """(rows, box_lo, box_hi) of the set-membership LP: every segment in the update's box [lo, hi];
    with a window (window_s > 0) and a previous consistent data box, the window's segments in
    [lo, hi] ∩ that box, which holds the truth (A2) and what the older segments said of it: a
    relaxation of the LP on every segment (their joint constraints dropped, their box kept), so
    still an enclosure, at a cost that stops growing with the data."""
    if window_s <= 0 or previous is None or rows.t1[0] > rows.t1[-1] - window_s:
        return rows, lo, hi
    box_lo, box_hi = np.maximum(lo, previous[0]), np.minimum(hi, previous[1])
    if np.any(box_lo > box_hi):  # the boxes do not meet: the caller reports it
        return rows, lo, hi
    return rows.since(rows.t1[-1] - window_s), box_lo, box_hi


def certified_lp_min(
    c: np.ndarray,
    A_ub: np.ndarray,
    b_ub: np.ndarray,
    lo_x: np.ndarray,
    hi_x: np.ndarray,
    *,
    solution: list | None = None,
) -> tuple[str, float]:
    """A certified lower bound on min c·x s.t. A_ub x ≤ b_ub, lo_x ≤ x ≤ hi_x (HiGHS dual simplex).

    The solver's answer is not trusted: the bound is recomputed from its dual multipliers y ≥ 0
    by weak duality, min c·x ≥ Σ_j min(r_j l_j, r_j u_j) − yᵀb with r = c + Aᵀy, which holds for
    ANY y ≥ 0, then padded for the rounding of its own float sums and rounded outward.
    Returns (status, bound): status "ok", "infeasible" or "failed" (bound NaN). `solution`, a
    list, receives the primal minimiser (the cutting planes of `physical.prune_box` use it).
    """
    res = linprog(
        c,
        A_ub=A_ub,
        b_ub=b_ub,
        bounds=np.stack([lo_x, hi_x], 1),
        method="highs-ds",
        options={"presolve": False},
    )
    if res.status == 2:
        return "infeasible", np.nan
    if res.status != 0:
        return "failed", np.nan
    if solution is not None:
        solution.append(res.x)
    y = np.maximum(-res.ineqlin.marginals, 0.0)
    r = c + A_ub.T @ y
    bound = np.sum(np.minimum(r * lo_x, r * hi_x)) - y @ b_ub
    bound -= _lp_bound_rounding(c, A_ub, b_ub, y, r, np.maximum(np.abs(lo_x), np.abs(hi_x)))
    return "ok", float(np.nextafter(bound, -np.inf))


def _lp_bound_rounding(c, A_ub, b_ub, y, r, x_mag):
    """What the float evaluation of the weak-duality bound may exceed the exact one by: r = c + Aᵀy
    is a sum of m + 1 terms that can cancel (its error scales with |c| + |A|ᵀ|y|, not |r|), then
    n + m products are summed (dot_rounding). Never below the former margin, 1e-12 of the terms."""
    m = len(y)
    r_error = dot_rounding(m + 1) * (np.abs(c) + np.abs(A_ub).T @ y) @ x_mag
    terms = np.abs(r) @ x_mag + y @ np.abs(b_ub)
    return max(1e-12 * terms, dot_rounding(len(r) + m) * terms + r_error) + 1e-300


def box_is_consistent(centre: np.ndarray, radius: np.ndarray) -> tuple[bool, float]:
    """Sufficient test that every θ in centre ± radius satisfies the LMI (pseudo-inertia ≻ 0):
    λ_min(J(centre)) > Σ_c radius_c ‖J(e_c)‖_2 (J is linear in θ)."""
    lam = np.linalg.eigvalsh(inertial.pseudo_inertia(centre)).min()
    basis_norm = np.array([np.linalg.norm(inertial.pseudo_inertia(e), 2) for e in np.eye(10)])
    return lam > radius @ basis_norm, lam
