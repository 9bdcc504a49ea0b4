"""Payload identification with a provable interval (paper Algorithm 1, Theorem 2).

Data model (momentum form, no accelerations). Over a segment [t_a, t_b] of a joint log,
    (Wm(b) - Wm(a) - ∫ Wc dt) θ = ∫ τ dt          (armature sits in Wm, RobotModel convention)
Split θ = (θ_e, θ_r) (identified end effector, rest of robot):
    Y_s θ_e = U_s(m),   Y_s = D_s[:, e],   U_s(m) = -D_s[:, r] θ_r + ∫ τ dt,   D = Wm(b)-Wm(a)-∫Wc
with the measurement vector m = (all torque samples, θ_r). U is LINEAR in m.

Estimate. θ0 = P(η*), η* = argmin ‖Y P(η) − U(m)‖² over the log-Cholesky coordinates η
(Drake MathematicalProgram + Ipopt or SNOPT with the exact gradient, then a trust-region
polish on the exact Hessian — Drake's Ipopt has no exact-Hessian callback; see
`solve_log_cholesky`). Warm start: the previous η or P⁻¹ of the unconstrained solution. By
default the rows are whitened and θ_r is marginalised with its box as a prior ("map", see
`_left_inverse`): the same problem on transformed data; it halves the bias a wrong θ_r puts on θ0.

Interval (why it is exact and not only first order). P is a diffeomorphism onto the
physically consistent set, so θ*(m) = P(η*(m)) is the least-squares solution over that set.
When the LMI is inactive, θ*(m') = L U(m') for every m' of [m] (L the least-squares left
inverse of Y, L = Y⁺ for unweighted rows), i.e. θ* is LINEAR in m and its Jacobian L ∂U/∂m is
constant (the paper's implicit-function formula reduces to it: the residual-curvature term of
the Hessian vanishes at an interior optimum, tested), so the mean-value form
θ*(m) + ∂θ*/∂m([m])([m]−m) of Theorem 2 is the EXACT hull  L U(m) ± |L ∂U/∂m| rad([m]).
Moreover, whatever the LMI does, the true θ_e is consistent and satisfies Y θ_e = U(m_true) − e
with m_true ∈ [m] and |e| ≤ the quadrature-error term, so θ_e = L(U(m_true) − e) for ANY left
inverse L: the box encloses the truth in every case. `case` says which one applies:
"interior" (the whole box is physically consistent: exact hull of θ*([m])), "interior_at_m"
(LMI inactive at m but active somewhere in the box; still an enclosure of the truth),
"lmi_active" (θ0 near the LMI boundary, θ0 ≠ L U(m); the box is reported around L U(m)). So no
interval enclosure of the Jacobian is needed for the near-singular case: the linear-map box
stays valid there; it is reported, not replaced.
Two left inverses are used (whitened/θ_r-marginalised and bound-scaled rows) and their boxes
intersected; then an optional certified LP (`set_membership_bounds`, exact projection of the
feasible polytope, dual-certified) tightens the mass (default) or all parameters. Each update
is intersected with the published interval (or the prior). Any empty set — the two boxes, the
LP's polytope, the intersection, a torque faster than declared — is evidence that a declared
bound failed: consistency is latched off and the last consistent box is published unchanged
(never the gap between boxes, never wider than before, never outside the prior).

Error terms of the box, per parameter (all exact hulls of linear maps, then outward rounding):
    torque:  |L ∂U/∂τ| r_τ   with r_τ = (ratio·|τ_meas| + floor)/(1 − ratio) per sample
             (the declared bound |τ_meas − τ| ≤ ratio·|τ| + floor re-expressed on what we
             measure). ∫τ dt: a held torque (zero-order hold, the default) is integrated exactly
             by the left sum — sample k acts over [t_k, t_k+1], so no sample is shared by two
             segments; a continuous torque signal by the trapezoid (a shared boundary sample
             counted once, with both weights) plus `torque_rate_bound`.
    θ_r:     |L D_r| r_θr    with r_θr = max(theta_r_ratio·|θ_r nominal|, floor of its kind)
    quadrature: |L| e_s, e_s the bound of `quadrature_bound` on the error of the quadrature of
             ∫W_c θ dt for every θ in the parameter box, under its stated assumption (on every
             step the integrand is monotone or its rate stays within κ = 2 times the mean rates
             of the step and its neighbours); plus, for a continuous torque, the trapezoid's.
    rounding: L is a left inverse only up to E = LY − I: |E|(|centre| + radius) plus a relative
             pad for the float sums, then one ulp outward.
Segments are cut by time (horizon_s) and never span a step longer than max_gap_s (for a held
torque, nor 1.5 hold periods: a lost sample's held torque is unknown).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linprog  # imported here: its first import costs ~0.3 s

from . import inertial, regressors
from .uncertainty import ParameterFloors, parameter_radius

EPS = np.finfo(float).eps


class EstimatorError(ValueError):
    """Bad estimator input (too little data, wrong shapes, non-finite values)."""


@dataclass
class EstimatorSettings:
    horizon_s: float = 0.1
    max_gap_s: float = 0.05
    integration: str = "trapezoid"  # quadrature of ∫W_c dt: trapezoid | euler (paper's left sum)
    # What the logged torque is. "held": each sample is the torque a zero-order hold applies until
    # the next sample (the simulated arm, a digital controller logged at its own rate): ∫τ dt is
    # the left sum, exactly. "continuous": a signal sampled at the log instants whose rate is at
    # most torque_rate_limit_Nm_s (checked on the data): trapezoid plus its error bound.
    torque_signal: str = "held"
    hold_period_s: float | None = None  # held: a step longer than 1.5 hold periods is a gap
    torque_rate_limit_Nm_s: float = 200.0  # continuous: declared |dτ/dt| of the applied torque
    solver: str = "ipopt"  # ipopt | snopt
    torque_ratio: float = 0.025  # declared |τ_meas − τ| ≤ ratio·|τ| + floor
    torque_floor_Nm: float = 0.05
    theta_r_ratio: float = 0.05  # [θ_r] = θ_r ± max(ratio·|θ_r|, floor of its kind)
    theta_r_floor: ParameterFloors = field(default_factory=ParameterFloors)
    # κ of the quadrature bound (`quadrature_bound`, its assumption); ≥ 2 covers any integrand
    # that is monotone on each step, whatever its slope.
    quadrature_safety: float = 2.0
    # Above this share of a row's torque radius the quadrature term is reported as "motion not
    # resolved by the sampling" (an event; the bound still holds under its assumption).
    quadrature_warn_ratio: float = 1.0
    newton_steps: int = 50  # max iterations of the exact-Hessian trust-region polish after the NLP
    max_condition: float = 1e10  # above: not identifiable yet, keep the previous estimate
    # Rows scaled by 1 / (their declared error bound) before the least squares ("bound"), or the
    # paper's unweighted problem ("none"). Theorem 2 holds verbatim for the scaled problem
    # (any left inverse L of Y gives θ_e = L(U(m_true) − e)); scaling shrinks the worst case.
    row_weighting: str = "bound"
    # Set-membership refinement (beyond the paper): the exact projection of the polytope
    # {θ_e : ∃θ_r ∈ [θ_r], |Y θ_e + D_r θ_r − ∫τ| ≤ row bound} on the listed parameters, by LP,
    # certified by weak duality. "mass" (2 LPs), "all" (20 LPs) or "none".
    set_membership: str = "mass"
    lp_generators: int = 40  # θ_r entries kept as LP variables (the rest bounded per row)
    # Point estimate θ0: "map" (θ_r marginalised with its box as prior, rows whitened) or
    # "paper" (the paper's ‖Y P(η) − U‖², rows scaled per `row_weighting`); see _left_inverse.
    point_estimate: str = "map"

    @classmethod
    def from_scenario(cls, s):
        e = s.estimator
        return cls(horizon_s=e.horizon_s, max_gap_s=e.max_gap_s, integration=e.integration, solver=e.solver,
                   torque_signal=e.torque_signal, hold_period_s=e.hold_period_s or s.plant.time_step_s,
                   torque_rate_limit_Nm_s=e.torque_rate_limit_Nm_s, quadrature_safety=e.quadrature_safety,
                   torque_ratio=s.noise.declared_torque_ratio, torque_floor_Nm=s.noise.declared_torque_floor_Nm,
                   theta_r_ratio=s.noise.theta_r_ratio, theta_r_floor=s.noise.theta_r_floor,
                   set_membership=e.set_membership, point_estimate=e.point_estimate)

    def segment_gap_s(self):
        """Longest step a segment may span: max_gap_s, and for a held torque 1.5 hold periods
        (a longer step lost held samples whose torque is unknown)."""
        if self.torque_signal == "held" and self.hold_period_s:
            return min(self.max_gap_s, 1.5 * self.hold_period_s)
        return self.max_gap_s

    def torque_rule(self):
        """Quadrature of ∫τ dt: the exact left sum of a held torque, else the trapezoid."""
        return "euler" if self.torque_signal == "held" else "trapezoid"


# ---------------------------------------------------------------------------------------------
# Segmentation by time
# ---------------------------------------------------------------------------------------------
def segment_bounds(t, horizon_s, max_gap_s):
    """Inclusive sample index pairs (a, b) of segments of about horizon_s seconds.

    A segment ends at the first sample with t_b − t_a ≥ horizon_s; consecutive segments share
    their boundary sample; no segment spans a step longer than max_gap_s (after a gap a new
    segment starts at the sample after it). Returns (bounds (S, 2) int, next_start): next_start
    is the first sample of the unfinished tail (data from there on is not used yet).
    """
    t = np.asarray(t, float)
    if len(t) < 2:
        return np.zeros((0, 2), int), 0
    gap_after = np.flatnonzero(np.diff(t) > max_gap_s)  # step k -> k+1 is a gap
    run_starts = np.concatenate([[0], gap_after + 1])
    run_ends = np.concatenate([gap_after, [len(t) - 1]])
    out = []
    next_start = 0
    for r0, r1 in zip(run_starts, run_ends):
        a = r0
        tt = t[r0:r1 + 1]
        while True:
            k = np.searchsorted(tt, t[a] + horizon_s - 1e-12 * max(1.0, abs(t[a])), side="left") + r0
            if k > r1:
                break
            out.append((a, k))
            a = k
        next_start = a
    return np.asarray(out, int).reshape(-1, 2), int(next_start)


def sample_weights(t, a, b, integration):
    """Quadrature weights of samples a..b for ∫ over [t_a, t_b]."""
    dt = np.diff(t[a:b + 1])
    w = np.zeros(b - a + 1)
    if integration == "euler":  # paper: left Riemann sum
        w[:-1] = dt
    else:
        w[:-1] += 0.5 * dt
        w[1:] += 0.5 * dt
    return w


# ---------------------------------------------------------------------------------------------
# Integrated momentum-rate regressor: ∫ Wc dt per segment without forming Wc per sample
# ---------------------------------------------------------------------------------------------
def _inertia_basis():
    """(6, 6, 10) K with s^T K(x) = Σ_ab s_a x_b K[a, b, :] (K(x) θ = I(θ) x is linear in x)."""
    return np.stack([regressors.inertia_times(np.eye(6)[b])[:, :] for b in range(6)], 1)


_K_BASIS = _inertia_basis()


def _cross(a, b):
    """a × b on the last axis (np.cross is several times slower on small stacked vectors)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], -1)


def _to_body(R, p, x):
    """Motion vectors about the world origin (N, k, 6) -> body frame at (R (N,3,3), p (N,3))."""
    k = x.shape[1]
    w = x[..., :3]
    both = np.concatenate([w, x[..., 3:] + _cross(w, p[:, None, :])], 1) @ R  # rows times R = Rᵀ·
    return np.concatenate([both[:, :k], both[:, k:]], -1)


@dataclass
class _Factors:
    """Per-sample body-frame factors, per body i (lists of length n):
    screws[i] (2N, k_i, 6): rows 0..N-1 X_i⁻¹ dS_j/dt, rows N..2N-1 X_i⁻¹ S_j for the k_i
    ancestors j of i (joints[i]); twist_grav[i] (2N, 6): body twist V_i, then −A_g in body i.
    Then Wc_rigid[j, i-block] at sample k = (screw_rate ⊗ V + screw ⊗ (−A_g)) contracted with K."""

    joints: list
    screws: list
    twist_grav: list
    nsamp: int


def _pair_factors(tree, q, v):
    kin = regressors.forward_kinematics(tree, q, v)
    anc = tree.ancestors()
    nsamp = q.shape[0]
    g_world = np.concatenate([np.zeros(3), np.asarray(tree.gravity, float)])  # −A_g = +gravity
    joints, screws, twist_grav = [], [], []
    for i in range(tree.n):
        js = np.flatnonzero(anc[:, i])
        k = len(js)
        both = _to_body(kin.R[:, i], kin.p[:, i], np.concatenate(
            [kin.Sdot[:, js], kin.S[:, js], kin.V[:, i, None], np.broadcast_to(g_world, (nsamp, 1, 6))], 1))
        joints.append(js)
        screws.append(np.concatenate([both[:, :k], both[:, k:2 * k]], 0))
        twist_grav.append(np.concatenate([both[:, 2 * k], both[:, 2 * k + 1]], 0))
    return _Factors(joints, screws, twist_grav, nsamp)


def integrated_rate_regressor(tree, q, v, t, bounds, integration="trapezoid", factors=None):
    """∫ Wc_rigid dt over each segment (S, n, 10 n), exact quadrature of the per-sample Wc.

    Uses sᵀK(x) = Σ_ab s_a x_b K_ab: per segment and body one (k·6 × 2K)(2K × 6) product,
    instead of materialising the (N, n, 10n) per-sample regressor. Indices of `bounds` refer to
    the samples the factors were computed on.
    """
    n = tree.n
    if factors is None:
        factors = _pair_factors(tree, q, v)
    N = factors.nsamp
    kbasis = _K_BASIS.reshape(36, 10)
    out = np.zeros((len(bounds), n, 10 * n))
    weights = [sample_weights(t, a, b, integration) for a, b in bounds]
    for i in range(n):
        js = factors.joints[i]
        k = len(js)
        sT = factors.screws[i].transpose(1, 2, 0).reshape(k * 6, 2 * N)  # (k·6, 2N)
        x = factors.twist_grav[i]
        gram = np.empty((len(bounds), k * 6, 6))
        for s, (a, b) in enumerate(bounds):
            idx = np.r_[a:b + 1, N + a:N + b + 1]
            ww = np.concatenate([weights[s], weights[s]])
            gram[s] = sT[:, idx] @ (x[idx] * ww[:, None])
        out[:, js, 10 * i:10 * i + 10] = gram.reshape(len(bounds), k, 36) @ kbasis
    return out


def _segment_sums(values, t, bounds, integration):
    """∫ values dt per segment with the same quadrature, values (N, ...) -> (S, ...)."""
    out = np.empty((len(bounds),) + values.shape[1:])
    for s, (a, b) in enumerate(bounds):
        out[s] = np.tensordot(sample_weights(t, a, b, integration), values[a:b + 1], 1)
    return out


def _rate_blocks(factors, n):
    """Per body i: (i, its ancestor joints, W_c,rigid[:, joints, body i] at every sample (N, k, 10)),
    from Σ_ab s_a x_b K_ab = s · (x K), x K one (2N, 6)(6, 60) product per body."""
    N = factors.nsamp
    k_by_b = _K_BASIS.transpose(1, 0, 2).reshape(6, 60)  # (b, a·10)
    for i in range(n):
        s, xk = factors.screws[i], (factors.twist_grav[i] @ k_by_b).reshape(2 * N, 6, 10)
        yield i, factors.joints[i], s[:N] @ xk[:N] + s[N:] @ xk[N:]


def rate_regressor_samples(factors, n):
    """W_c,rigid at every sample (N, n, 10 n): the per-sample form of `integrated_rate_regressor`."""
    out = np.zeros((factors.nsamp, n, 10 * n))
    for i, joints, block in _rate_blocks(factors, n):
        out[:, joints, 10 * i:10 * i + 10] = block
    return out


def integrand_rates(t, factors, fric_cols, theta_centre, theta_radius):
    """Per step k and joint, a_k ≥ |f(t_k+1) − f(t_k)| / h_k for the integrand f = W_c θ and
    EVERY θ in θ_centre ± θ_radius (the mean of ḟ over the step), (N − 1, n). W_c = rigid part
    (from the factors, body by body: never the whole (N, n, 14 n) array) + fric_cols (N, n, 4 n)."""
    n = fric_cols.shape[1]
    f = fric_cols @ theta_centre[10 * n:]
    spread = np.abs(np.diff(fric_cols, axis=0)) @ theta_radius[10 * n:]
    for i, joints, block in _rate_blocks(factors, n):
        body = slice(10 * i, 10 * i + 10)
        f[:, joints] += block @ theta_centre[body]
        spread[:, joints] += np.abs(np.diff(block, axis=0)) @ theta_radius[body]
    return (np.abs(np.diff(f, axis=0)) + spread) / np.diff(t)[:, None]


def quadrature_bound(t, rates, bounds, integration, safety):
    """Per segment and joint, a bound on |∫ f dt − quadrature(f)| for the integrand f = W_c θ.

    Assumption (κ = safety ≥ 2): on every step, f is monotone, or |ḟ| ≤ κ·max(a_k−1, a_k, a_k+1)
    (the mean rates of the step and its neighbours in the segment, `integrand_rates`). Per step
    the trapezoid errs by at most h·|Δf|/2 = h² a_k/2 when f is monotone there, and by L h²/4
    when |ḟ| ≤ L; the left sum by h² a_k and L h²/2. Both cases are covered by
        c·κ·h_k²·max(a_k−1, a_k, a_k+1),   c = 1/4 (trapezoid), 1/2 (left sum).
    Under a zero-order-hold torque ḟ jumps only at the samples, so inside a step f is as smooth as
    the arm's dynamics; the neighbours cover an extremum of f inside a step (where a_k ~ 0).
    """
    c = 0.5 if integration == "euler" else 0.25
    h2 = np.diff(t) ** 2
    out = np.zeros((len(bounds), rates.shape[1]))
    for s, (a, b) in enumerate(bounds):
        r = rates[a:b]  # the steps of this segment only: independent of how data was chunked
        local = r.copy()
        local[1:] = np.maximum(local[1:], r[:-1])
        local[:-1] = np.maximum(local[:-1], r[1:])
        out[s] = c * safety * (h2[a:b] @ local)
    return out


def torque_rate_bound(t, tau_meas, radius, bounds, rate_limit):
    """Continuous torque signal with |dτ/dt| ≤ rate_limit: per segment and joint the trapezoid
    error bound rate_limit·Σ h²/4, and per segment whether the measurements contradict the
    declared rate (|Δτ_meas| > rate_limit·h + r_k + r_k+1 on some step: the assumption failed)."""
    h = np.diff(t)
    slack = rate_limit * h[:, None] + radius[:-1] + radius[1:]
    bad_step = np.any(np.abs(np.diff(tau_meas, axis=0)) > slack, 1)
    err = np.zeros((len(bounds), tau_meas.shape[1]))
    bad = np.zeros(len(bounds), bool)
    for s, (a, b) in enumerate(bounds):
        err[s] = 0.25 * rate_limit * np.sum(h[a:b] ** 2)
        bad[s] = bool(np.any(bad_step[a:b]))
    return err, bad


# ---------------------------------------------------------------------------------------------
# Segment rows: Y, D_r, ∫τ and what the interval needs
# ---------------------------------------------------------------------------------------------
@dataclass
class SegmentRows:
    t0: np.ndarray  # (S,) segment start/end times
    t1: np.ndarray
    Y: np.ndarray  # (S, n, 10)
    D_r: np.ndarray  # (S, n, nr): ∂U/∂θ_r = −D_r
    T: np.ndarray  # (S, n): ∫ τ dt
    w_first: np.ndarray  # (S,) quadrature weight of the first / last sample
    w_last: np.ndarray
    r_first: np.ndarray  # (S, n) torque radius of the first / last sample
    r_last: np.ndarray
    r_inner: np.ndarray  # (S, n) Σ_inner w_k r_k
    r_inner_sq: np.ndarray  # (S, n) Σ_inner w_k² r_k² (noise scale for the point estimate)
    shared_prev: np.ndarray  # (S,) bool: first sample is the previous segment's last
    quad: np.ndarray  # (S, n) quadrature-error bound (`quadrature_bound`, `torque_rate_bound`)
    violated: np.ndarray  # (S,) bool: the data contradict a declared assumption (torque rate)
    end_index: np.ndarray  # (S,) global index of the last sample (bookkeeping)
    start_index: np.ndarray

    @classmethod
    def empty(cls, n, nr):
        z = lambda *s: np.zeros(s)  # noqa: E731
        return cls(z(0), z(0), z(0, n, 10), z(0, n, nr), z(0, n), z(0), z(0), z(0, n), z(0, n), z(0, n), z(0, n),
                   np.zeros(0, bool), z(0, n), np.zeros(0, bool), np.zeros(0, int), np.zeros(0, int))

    def __len__(self):
        return len(self.t0)

    def concat(self, other):
        vals = {k: np.concatenate([getattr(self, k), getattr(other, k)]) for k in self.__dataclass_fields__}
        return SegmentRows(**vals)


def torque_radius(tau_meas, settings):
    """Per-sample bound on |τ_true − τ_meas| from the declared |τ_meas − τ| ≤ ratio|τ| + floor."""
    ratio = settings.torque_ratio
    if ratio >= 1:
        raise EstimatorError("noise.declared_torque_ratio must be < 1")
    return (ratio * np.abs(tau_meas) + settings.torque_floor_Nm) / (1.0 - ratio)


def build_segment_rows(robot, t, q, v, tau, bounds, settings, theta_box=None, index_offset=0):
    """Y, D_r, ∫τ and interval bookkeeping for the given segments (vectorized over samples).

    theta_box: (centre, radius) over all 14 n parameters, the box the true θ lies in, for the
    quadrature bound (None: the model's θ, zero radius).
    """
    n = robot.n
    ee = robot.ee_slice
    rest = robot.rest_mask()
    S = len(bounds)
    if S == 0:
        return SegmentRows.empty(n, int(rest.sum()))
    lo, hi = int(bounds[:, 0].min()), int(bounds[:, 1].max())
    loc = bounds - lo
    tt, qq, vv, ta = t[lo:hi + 1], q[lo:hi + 1], v[lo:hi + 1], tau[lo:hi + 1]
    integ = settings.integration
    factors = _pair_factors(robot.tree, qq, vv)
    wc_rigid = integrated_rate_regressor(robot.tree, qq, vv, tt, loc, integ, factors)
    rate_fric = regressors.friction_columns(vv, kind="rate", smoothing_velocity=robot.coulomb_smoothing)
    wc_fric = _segment_sums(rate_fric, tt, loc, integ)
    ends = np.unique(loc.ravel())
    wm = robot.momentum_regressor(qq[ends], vv[ends])
    pos = {k: r for r, k in enumerate(ends)}
    wm_a = wm[[pos[a] for a in loc[:, 0]]]
    wm_b = wm[[pos[b] for b in loc[:, 1]]]
    D = wm_b - wm_a - np.concatenate([wc_rigid, wc_fric], -1)
    rule = settings.torque_rule()
    T = _segment_sums(ta, tt, loc, rule)
    r = torque_radius(ta, settings)
    w_first = np.empty(S)
    w_last = np.empty(S)
    r_inner = np.empty((S, n))
    r_inner_sq = np.empty((S, n))
    for s, (a, b) in enumerate(loc):
        w = sample_weights(tt, a, b, rule)
        w_first[s], w_last[s] = w[0], w[-1]
        r_inner[s] = w[1:-1] @ r[a + 1:b]
        r_inner_sq[s] = w[1:-1] ** 2 @ r[a + 1:b] ** 2
    shared_prev = np.zeros(S, bool)
    shared_prev[1:] = loc[1:, 0] == loc[:-1, 1]
    centre, radius = (robot.theta, np.zeros_like(robot.theta)) if theta_box is None else theta_box
    rates = integrand_rates(tt, factors, rate_fric, centre, radius)
    quad = quadrature_bound(tt, rates, loc, integ, settings.quadrature_safety)
    violated = np.zeros(S, bool)
    if settings.torque_signal == "continuous":
        err, violated = torque_rate_bound(tt, ta, r, loc, settings.torque_rate_limit_Nm_s)
        quad = quad + err
    return SegmentRows(t0=tt[loc[:, 0]], t1=tt[loc[:, 1]], Y=D[..., ee], D_r=D[..., rest], T=T,
                       w_first=w_first, w_last=w_last, r_first=r[loc[:, 0]], r_last=r[loc[:, 1]],
                       r_inner=r_inner, r_inner_sq=r_inner_sq, shared_prev=shared_prev, quad=quad,
                       violated=violated, start_index=bounds[:, 0] + index_offset,
                       end_index=bounds[:, 1] + index_offset)


# ---------------------------------------------------------------------------------------------
# The nonlinear least squares in log-Cholesky coordinates
# ---------------------------------------------------------------------------------------------
def ls_cost_terms(Y, U):
    """A = YᵀY, b = YᵀU, c = UᵀU so that ‖Yθ − U‖² = θᵀAθ − 2bᵀθ + c."""
    return Y.T @ Y, Y.T @ U, float(U @ U)


def _centred(A, b, c):
    """θ_c = A⁻¹b and J_min, so that ½(θᵀAθ − 2bᵀθ + c) = ½(θ−θ_c)ᵀA(θ−θ_c) + J_min: the
    centred form keeps the cost accurate near the optimum (no cancellation of large terms)."""
    theta_c = np.linalg.solve(A, b)
    return theta_c, 0.5 * max(c - b @ theta_c, 0.0)


def cost_grad_hess(eta, A, b, c, centred=None):
    """J(η) = ½‖Y P(η) − U‖² and its exact gradient and Hessian (paper appendix, eq. D_ee)."""
    theta_c, jmin = centred or _centred(A, b, c)
    theta = inertial.log_cholesky_to_theta(eta)
    jac = inertial.log_cholesky_jacobian(eta)
    d = theta - theta_c
    r = A @ d  # = Yᵀ(Yθ − U)
    J = 0.5 * d @ r + jmin
    g = jac.T @ r
    H = jac.T @ A @ jac + np.einsum("i,ikl->kl", r, inertial.log_cholesky_hessian(eta))
    return J, g, H


@dataclass
class SolveResult:
    eta: np.ndarray
    theta: np.ndarray
    cost: float
    grad_norm: float
    solver: str
    success: bool
    message: str = ""
    newton_steps: int = 0


_THETA_OF_J = np.stack([inertial.theta_from_pseudo_inertia(e.reshape(4, 4)) for e in np.eye(16)], 1)  # θ = L vec(J)
_OFFDIAG = [(0, 1), (0, 2), (1, 2), (0, 3), (1, 3), (2, 3)]  # η[4:] order of inertial.py
_OFF_R = np.array([rc[0] for rc in _OFFDIAG])
_OFF_C = np.array([rc[1] for rc in _OFFDIAG])


def cost_and_gradient(eta, A, b, c, centred=None):
    """J(η) and its exact gradient, the fast path used inside the NLP (≈ 20 µs)."""
    theta_c, jmin = centred or _centred(A, b, c)
    a = np.exp(eta[0])
    u = np.zeros((4, 4))
    u[[0, 1, 2], [0, 1, 2]] = np.exp(eta[1:4])
    u[3, 3] = 1.0
    u[_OFF_R, _OFF_C] = eta[4:]
    u *= a
    theta = _THETA_OF_J @ (u @ u.T).ravel()
    d = theta - theta_c
    r = A @ d
    J = 0.5 * d @ r + jmin
    rm = (_THETA_OF_J.T @ r).reshape(4, 4)
    G = (rm + rm.T) @ u  # dJ/dU
    g = np.empty(10)
    g[0] = np.sum(G * u)
    g[1:4] = np.diag(G)[:3] * np.diag(u)[:3]
    g[4:] = G[_OFF_R, _OFF_C] * a
    return J, g


ETA_LOWER = np.array([-20.0, -20, -20, -20] + [-1e4] * 6)
ETA_UPPER = np.array([20.0, 20, 20, 20] + [1e4] * 6)


def _solver(name):
    from pydrake.solvers import IpoptSolver, SnoptSolver

    if name == "snopt":
        s = SnoptSolver()
        if s.available() and s.enabled():
            return s, "snopt"
        return IpoptSolver(), "ipopt (snopt unavailable)"
    return IpoptSolver(), "ipopt"


def solve_log_cholesky(A, b, c, eta0, solver="ipopt", newton_steps=50, scale=None, max_iterations=20,
                       max_time_s=0.08):
    """min_η ½‖Y P(η) − U‖² with Drake MathematicalProgram.

    The cost is a Python function evaluated on AutoDiffXd that returns the EXACT gradient
    (chain rule through dP/dη, no forward-mode over the data). Drake's Ipopt interface does not
    expose an exact Hessian callback (its eval_h is not implemented: Ipopt runs with a
    limited-memory quasi-Newton Hessian, and "hessian_approximation exact" aborts), so the answer
    is then polished by a trust-region Newton method on the exact Hessian (`cost_grad_hess`),
    kept only if it lowers the cost. Ipopt is capped (iterations, time): L-BFGS is slow on this
    badly scaled map, and the exact-Hessian polish converges in a few steps from its answer. When the unconstrained
    optimum is not physically consistent the infimum sits on the LMI boundary and is not attained
    in η: the solvers then stop at an iterate close to it (reported, not an error).
    """
    from pydrake.autodiffutils import AutoDiffXd, ExtractGradient, ExtractValue
    from pydrake.solvers import MathematicalProgram, SolverOptions

    # Cost scaling: Ipopt's tolerances are absolute; scale so the start costs O(1).
    # (Cost scaled by trace(A): the scaled Hessian in θ has eigenvalues ≤ 1.)
    scale = scale or max(np.trace(A), 1e-300)
    centred = _centred(A, b, c)

    def cost(x):
        if x.dtype == object:
            J, g = cost_and_gradient(ExtractValue(x).ravel(), A, b, c, centred)
            return AutoDiffXd(J / scale, (g / scale) @ ExtractGradient(x))
        return cost_and_gradient(np.asarray(x, float), A, b, c, centred)[0] / scale

    prog = MathematicalProgram()
    x = prog.NewContinuousVariables(10, "eta")
    prog.AddCost(cost, vars=x)
    # Keep η finite: when the unconstrained optimum is not physically consistent the infimum
    # lies on the LMI boundary (η → ∞); these bounds stop the search e^-20 away from it.
    prog.AddBoundingBoxConstraint(ETA_LOWER, ETA_UPPER, x)
    eta0 = np.clip(eta0, ETA_LOWER, ETA_UPPER)
    prog.SetInitialGuess(x, eta0)
    slv, name = _solver(solver)
    opts = SolverOptions()
    if name == "ipopt":
        opts.SetOption(slv.solver_id(), "print_level", 0)
        opts.SetOption(slv.solver_id(), "tol", 1e-9)
        # Warm start: a small barrier parameter and bound multipliers, so a start at the
        # optimum is accepted at iteration 0 instead of being pushed off by the barrier.
        opts.SetOption(slv.solver_id(), "mu_init", 1e-8)
        opts.SetOption(slv.solver_id(), "bound_mult_init_val", 1e-8)
        opts.SetOption(slv.solver_id(), "acceptable_tol", 1e-6)
        opts.SetOption(slv.solver_id(), "acceptable_iter", 3)
        opts.SetOption(slv.solver_id(), "max_iter", max_iterations)
        opts.SetOption(slv.solver_id(), "max_cpu_time", max_time_s)
    else:
        opts.SetOption(slv.solver_id(), "Major iterations limit", max_iterations)
    import logging

    drake_log = logging.getLogger("drake")
    level = drake_log.level
    drake_log.setLevel(logging.ERROR)  # an iteration/time cap is expected near the LMI boundary
    try:
        res = slv.Solve(prog, eta0, opts)
        eta = np.asarray(res.GetSolution(x), float)
        ok = bool(res.is_success()) and np.all(np.isfinite(eta))
        msg = str(res.get_solution_result())
    except Exception as err:  # solver crash -> fall back to the start point, logged
        eta, ok, msg = np.asarray(eta0, float), False, f"solver error: {err}"
    finally:
        drake_log.setLevel(level)
    if not np.all(np.isfinite(eta)):
        eta = np.asarray(eta0, float)
    # Exact-Hessian polish: trust-region Newton (scipy trust-exact) on our exact gradient and
    # Hessian, from the NLP's answer; kept only if it lowers the cost and stays in the η box.
    J = cost_and_gradient(eta, A, b, c, centred)[0]
    steps = 0
    polished = False
    if newton_steps > 0:
        from scipy.optimize import minimize

        with np.errstate(over="ignore", invalid="ignore"):
            pol = minimize(lambda e: cost_and_gradient(e, A, b, c, centred)[0] / scale, eta,
                           jac=lambda e: cost_and_gradient(e, A, b, c, centred)[1] / scale,
                           hess=lambda e: cost_grad_hess(e, A, b, c, centred)[2] / scale,
                           method="trust-exact", options={"maxiter": newton_steps, "gtol": 1e-12})
        if np.all(np.isfinite(pol.x)) and np.all(pol.x >= ETA_LOWER) and np.all(pol.x <= ETA_UPPER):
            Jp = cost_and_gradient(pol.x, A, b, c, centred)[0]
            if np.isfinite(Jp) and Jp <= J:
                eta, J, steps = pol.x, Jp, int(pol.nit)
                polished = bool(pol.success)
    g = cost_and_gradient(eta, A, b, c, centred)[1]
    # Stationary to working precision (relative to the curvature scale) counts as solved.
    ok = ok or polished or bool(np.linalg.norm(g) <= 1e-9 * scale * max(1.0, np.linalg.norm(eta)))
    return SolveResult(eta=eta, theta=inertial.log_cholesky_to_theta(eta), cost=J, grad_norm=float(np.linalg.norm(g)),
                       solver=name, success=ok, message=msg, newton_steps=steps)


def ift_sensitivity(eta, A, b, dU_dm_Y):
    """Paper appendix: ∂θ*/∂m = −P_η (∂²J/∂η²)⁻¹ ∂²J/∂m∂η at η, with dU_dm_Y = Yᵀ ∂U/∂m.

    At an interior least-squares optimum this equals Y⁺ ∂U/∂m (the residual-curvature term of
    the Hessian vanishes with the gradient); used by the tests to check that identity.
    """
    _, _, H = cost_grad_hess(eta, A, b, 0.0)
    jac = inertial.log_cholesky_jacobian(eta)
    mixed = -jac.T @ dU_dm_Y  # ∂²J/∂η∂m
    return -jac @ np.linalg.solve(H, mixed)


def nearest_consistent(theta, rel_floor=1e-6):
    """θ whose pseudo-inertia is J(θ) with eigenvalues floored at rel_floor·λ_max (Frobenius
    projection onto the consistent set; equals θ when θ is already safely consistent)."""
    lam, vec = np.linalg.eigh(inertial.pseudo_inertia(theta))
    floor = rel_floor * max(lam.max(), 1e-9)
    if lam.min() > floor:
        return np.asarray(theta, float)
    return inertial.theta_from_pseudo_inertia((vec * np.maximum(lam, floor)) @ vec.T)


# ---------------------------------------------------------------------------------------------
# Interval (Theorem 2, exact hull of the linear map)
# ---------------------------------------------------------------------------------------------
@dataclass
class Estimate:
    theta_e: np.ndarray  # θ0 = P(η*) of the end effector (10)
    lower: np.ndarray  # [θ_e] (10), intersected with the previous interval
    upper: np.ndarray
    theta: np.ndarray  # whole robot nominal (14 n)
    theta_lower: np.ndarray  # whole robot interval (14 n)
    theta_upper: np.ndarray
    eta: np.ndarray
    theta_ls: np.ndarray  # unconstrained least squares Y⁺U(m) (centre of this update's box)
    update_lower: np.ndarray  # this update's box before intersection
    update_upper: np.ndarray
    radius_torque: np.ndarray
    radius_theta_r: np.ndarray
    radius_quadrature: np.ndarray
    radius_rounding: np.ndarray
    case: str  # interior | interior_at_m | lmi_active | not_identifiable | prior
    consistent: bool  # False from the first update whose data contradict a declared bound (latched)
    cond_Y: float
    num_segments: int
    num_samples: int
    solver: dict = field(default_factory=dict)
    message: str = ""
    problems: list = field(default_factory=list)  # this update's evidence that an assumption failed
    quadrature_ratio: float = 0.0  # max over rows of quadrature bound / torque radius
    update_time_s: float = 0.0

    @property
    def widths(self):
        return self.upper - self.lower

    def contains(self, theta_e, tol=0.0):
        return bool(np.all((self.lower - tol <= theta_e) & (theta_e <= self.upper + tol)))

    def to_json(self, names=inertial.NAMES):
        f = lambda x: [float(v) for v in np.asarray(x).ravel()]  # noqa: E731
        return {"nominal": f(self.theta_e), "lower": f(self.lower), "upper": f(self.upper), "names": list(names),
                "widths": f(self.widths), "theta_ls": f(self.theta_ls), "update_lower": f(self.update_lower),
                "update_upper": f(self.update_upper), "radius": {"torque": f(self.radius_torque),
                "theta_r": f(self.radius_theta_r), "quadrature": f(self.radius_quadrature),
                "rounding": f(self.radius_rounding)}, "case": self.case, "consistent": self.consistent,
                "cond_Y": float(self.cond_Y), "num_segments": int(self.num_segments),
                "num_samples": int(self.num_samples), "solver": self.solver, "message": self.message,
                "problems": list(self.problems), "quadrature_ratio": float(self.quadrature_ratio),
                "update_time_s": float(self.update_time_s)}


def _pinv(Y2):
    """Y⁺ = R⁻¹Qᵀ (QR, better conditioned than the normal equations) and cond(Y)."""
    Q, R = np.linalg.qr(Y2)
    sv = np.linalg.svd(R, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else np.inf
    if not np.isfinite(cond):
        return None, cond
    return np.linalg.solve(R, Q.T), cond


def _torque_row_radius(rows: SegmentRows):
    """(S, n) declared bound of the torque part of each row, Σ_k w_k r_k."""
    return rows.w_first[:, None] * rows.r_first + rows.w_last[:, None] * rows.r_last + rows.r_inner


def row_bounds(rows: SegmentRows, rad_r):
    """Declared error bound of each row of U (torque + θ_r + quadrature), (S n,); rad_r the
    half-widths of [θ_r]."""
    r_thr = np.abs(rows.D_r) @ rad_r
    return (_torque_row_radius(rows) + r_thr + rows.quad).ravel()


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
        sig = np.sqrt((rows.w_first[:, None] ** 2 * rows.r_first ** 2 + rows.w_last[:, None] ** 2 * rows.r_last ** 2
                       + rows.r_inner_sq) / 3.0).ravel() + rows.quad.ravel()
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


def interval_hull(rows: SegmentRows, theta_r, rad_r, settings):
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
    rad_tau = (np.abs(first) * rows.r_first).sum((1, 2)) + (np.abs(last) * rows.r_last).sum((1, 2)) \
        + (np.abs(G) * rows.r_inner).sum((1, 2))
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
    return dict(centre=centre, rad_torque=rad_tau, rad_theta_r=rad_theta_r, rad_quad=rad_quad, rad_round=rad_round,
                U=U, A=A, b=b, c=c, pinv=L), cond


def set_membership_bounds(rows: SegmentRows, theta_r, rad_r, settings, box_lo, box_hi, params):
    """Certified [min, max] of θ_e[i] (i in params) over the feasible polytope, by LP.

    Variables x = (θ_e, θ_r); rows |Y θ_e + D_r θ_r − ∫τ| ≤ Σ_k w_k r_k + quadrature term (a
    boundary sample shared by two segments is let vary independently in each: a relaxation,
    so still an enclosure); θ_r in its box; θ_e in the Theorem-2 box (already proven).
    The LP solver's answer is not trusted: each bound is recomputed from its dual multipliers
    y ≥ 0 by weak duality, min c·x ≥ Σ_j min(r_j l_j, r_j u_j) − yᵀb with r = c + Aᵀy, which
    holds for ANY y ≥ 0. Returns (lo, hi, feasible); lo/hi are NaN where not refined.
    """
    S, n = rows.T.shape
    Y2 = rows.Y.reshape(S * n, 10)
    Dr2 = rows.D_r.reshape(S * n, -1)
    # Order reduction of the θ_r zonotope: the lp_generators entries with the largest effect
    # stay LP variables; the others are fixed at nominal and their worst case |D_r,c| rad_c is
    # added to each row's bound (a relaxation, so still an enclosure; ~no loss at 40 of 88).
    effect = (np.abs(Dr2) * rad_r).sum(0)
    keep = np.zeros(len(theta_r), bool)
    keep[np.argsort(-effect)[:settings.lp_generators]] = True
    keep &= effect > 0
    fixed = Dr2[:, ~keep] @ theta_r[~keep]
    dropped = (np.abs(Dr2[:, ~keep]) * rad_r[~keep]).sum(1)
    A = np.hstack([Y2, Dr2[:, keep]])
    R = ((_torque_row_radius(rows) + rows.quad).ravel() + dropped) * (1 + 1e-9)
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
            res = linprog(c, A_ub=A_ub, b_ub=b_ub, bounds=np.stack([lo_x, hi_x], 1), method="highs-ds",
                          options={"presolve": False})
            if res.status == 2:  # infeasible: the data contradict the declared bounds
                return out_lo, out_hi, False
            if res.status != 0:
                continue
            y = np.maximum(-res.ineqlin.marginals, 0.0)
            r = c + A_ub.T @ y
            bound = np.sum(np.minimum(r * lo_x, r * hi_x)) - y @ b_ub
            # Rounding of the certificate's own float sums (relative, generous).
            bound -= 1e-12 * (np.abs(r) @ np.maximum(np.abs(lo_x), np.abs(hi_x)) + np.abs(y) @ np.abs(b_ub)) + 1e-300
            if sign > 0:
                out_lo[i] = np.nextafter(bound, -np.inf)
            else:
                out_hi[i] = np.nextafter(-bound, np.inf)
    return out_lo, out_hi, True


def _box_is_consistent(centre, radius):
    """Sufficient test that every θ in centre ± radius satisfies the LMI (pseudo-inertia ≻ 0):
    λ_min(J(centre)) > Σ_c radius_c ‖J(e_c)‖_2 (J is linear in θ)."""
    lam = np.linalg.eigvalsh(inertial.pseudo_inertia(centre)).min()
    basis_norm = np.array([np.linalg.norm(inertial.pseudo_inertia(e), 2) for e in np.eye(10)])
    return lam > radius @ basis_norm, lam


# ---------------------------------------------------------------------------------------------
# Incremental estimator (Algorithm 1, chunk by chunk)
# ---------------------------------------------------------------------------------------------
class IncrementalEstimator:
    """Accepts joint-log chunks; keeps per-segment rows so old segments are never recomputed.

    prior: optional (lower, upper) of θ_e to intersect with (e.g. the paper's Table II box). It
    also bounds θ_e in the quadrature term; without one that term takes |θ_e − θ_e0| ≤ |θ_e0|
    (θ_e0 = prior_nominal, or the model's end effector).

    Consistency is latched: the first update whose data contradict a declared bound (two
    enclosures that do not meet, an infeasible set-membership LP, a box disjoint from the
    published one, a torque faster than declared) sets `consistent` False for good, and from then
    on the last consistent box (or the prior) is published unchanged: a published box is never
    outside the previous one, nor outside the prior.
    """

    def __init__(self, robot, settings: EstimatorSettings | None = None, prior=None, prior_nominal=None):
        self.robot = robot
        self.settings = st = settings or EstimatorSettings()
        if st.integration not in ("trapezoid", "euler"):
            raise EstimatorError(f"estimator.integration: {st.integration!r} is not trapezoid or euler")
        if st.torque_signal not in ("held", "continuous"):
            raise EstimatorError(f"estimator.torque_signal: {st.torque_signal!r} is not held or continuous")
        if st.quadrature_safety < 2:
            raise EstimatorError(f"estimator.quadrature_safety: {st.quadrature_safety} must be >= 2")
        self.n = robot.n
        rest = robot.rest_mask()
        self.theta_r = robot.theta[rest].copy()
        self.theta_r_radius = parameter_radius(robot, st.theta_r_ratio, st.theta_r_ratio, st.theta_r_floor)[rest]
        self.rows = SegmentRows.empty(self.n, len(self.theta_r))
        self._pending = None  # (t, q, v, tau) of the unfinished tail
        self._consumed = 0  # global index of the first pending sample
        self.num_samples = 0
        self.prior = None if prior is None else (np.asarray(prior[0], float), np.asarray(prior[1], float))
        nominal = robot.theta_e if prior_nominal is None else np.asarray(prior_nominal, float)
        self.prior_nominal = nominal.copy()  # published before the first update (need not be consistent)
        self.eta = inertial.theta_to_log_cholesky(nominal) if inertial.is_physically_consistent(nominal) \
            else np.zeros(10)
        self.estimate: Estimate | None = None
        self.consistent = True  # latched: False from the first inconsistent update on
        self.update_times_s = []
        self.messages = []

    # -- data -------------------------------------------------------------------------------
    def add(self, t, q, v, tau):
        """Append samples (any chunk size); builds the segments that became complete."""
        t = np.atleast_1d(np.asarray(t, float))
        q, v, tau = (np.atleast_2d(np.asarray(x, float)) for x in (q, v, tau))
        if q.shape != (len(t), self.n) or v.shape != q.shape or tau.shape != q.shape:
            raise EstimatorError(f"expected {self.n} joints per sample, got q {q.shape}, v {v.shape}, tau {tau.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q)) and np.all(np.isfinite(v)) and np.all(np.isfinite(tau))):
            raise EstimatorError("NaN or inf in the estimator input")
        if self._pending is not None:
            if len(t) and t[0] <= self._pending[0][-1]:
                raise EstimatorError(f"time is not strictly increasing at t={t[0]:.6g}")
            t, q, v, tau = (np.concatenate([a, b]) for a, b in zip(self._pending, (t, q, v, tau)))
        if np.any(np.diff(t) <= 0):
            raise EstimatorError("time is not strictly increasing")
        self.num_samples += len(t) - (0 if self._pending is None else len(self._pending[0]))
        bounds, next_start = segment_bounds(t, self.settings.horizon_s, self.settings.segment_gap_s())
        if len(bounds):
            new = build_segment_rows(self.robot, t, q, v, tau, bounds, self.settings, self.theta_box(), self._consumed)
            if len(self.rows) and len(new) and new.start_index[0] == self.rows.end_index[-1]:
                new.shared_prev[0] = True
            self.rows = self.rows.concat(new)
        self._consumed += next_start
        self._pending = tuple(x[next_start:] for x in (t, q, v, tau))
        return len(bounds)

    def theta_box(self):
        """(centre, radius) of the box the whole-robot θ lies in: [θ_r] and the published [θ_e]
        (or the prior), for the quadrature bound."""
        centre, radius = self.robot.theta.copy(), np.zeros(14 * self.n)
        radius[self.robot.rest_mask()] = self.theta_r_radius
        ee = self.robot.ee_slice
        box = (self.estimate.lower, self.estimate.upper) if self.estimate is not None else self.prior
        if box is not None and np.all(np.isfinite(box[0])) and np.all(np.isfinite(box[1])):
            centre[ee], radius[ee] = 0.5 * (box[0] + box[1]), 0.5 * (box[1] - box[0])
        else:
            centre[ee], radius[ee] = self.prior_nominal, np.abs(self.prior_nominal)
        return centre, radius

    # -- estimate ---------------------------------------------------------------------------
    def update(self):
        """Algorithm 1 on all segments so far; returns the Estimate (also kept in .estimate)."""
        start = time.perf_counter()
        robot, st = self.robot, self.settings
        S = len(self.rows)
        if S * self.n < 10:
            hint = "" if st.segment_gap_s() == st.max_gap_s else (
                f" (held torque: a step longer than {st.segment_gap_s():.3g} s, 1.5 hold periods, ends a segment; "
                "for a log sampled slower than its controller set estimator.hold_period_s or "
                "estimator.torque_signal: continuous)")
            raise EstimatorError(f"too little data: {S} segment(s) of {st.horizon_s} s; need at least "
                                 f"{int(np.ceil(10 / self.n))} gap-free segments{hint}")
        hull, cond = interval_hull(self.rows, self.theta_r, self.theta_r_radius, st)
        prev = self.estimate
        if hull is None or cond > st.max_condition:
            return self._finish(self._prior_estimate(cond, S, f"not identifiable yet (cond(Y) = {cond:.3g})"), start)
        centre = hull["centre"]
        A, b, c = hull["A"], hull["b"], hull["c"]
        # Warm start: previous η, or P⁻¹ of the unconstrained solution when it is consistent
        # (then it is the optimum and the NLP only confirms it) — whichever costs less.
        starts = [self.eta, inertial.theta_to_log_cholesky(nearest_consistent(centre))]
        eta0 = min(starts, key=lambda e: cost_grad_hess(e, A, b, c)[0])
        sol = solve_log_cholesky(A, b, c, eta0, st.solver, st.newton_steps)
        if not np.all(np.isfinite(sol.theta)):
            sol.eta, sol.theta = self.eta, inertial.log_cholesky_to_theta(self.eta)
            self.messages.append("solver failed; kept the previous estimate")
        radius = hull["rad_torque"] + hull["rad_theta_r"] + hull["rad_quad"] + hull["rad_round"]
        lo = np.nextafter(centre - radius, -np.inf)
        hi = np.nextafter(centre + radius, np.inf)
        # Evidence that a declared assumption failed (each one empties the set the truth is in).
        problems = []
        if np.any(self.rows.violated):
            problems.append(f"the measured torque changes faster than the declared {st.torque_rate_limit_Nm_s} N·m/s "
                            f"in {int(self.rows.violated.sum())} segment(s)")
        # The same hull with the other left inverse (rows scaled by their declared bound): also
        # an enclosure, often tighter on the mass; keep the intersection.
        if st.point_estimate == "map":
            alt, _ = interval_hull(self.rows, self.theta_r, self.theta_r_radius,
                                   replace(st, point_estimate="paper", row_weighting="bound"))
            if alt is not None:
                r_alt = alt["rad_torque"] + alt["rad_theta_r"] + alt["rad_quad"] + alt["rad_round"]
                lo_alt = np.maximum(lo, np.nextafter(alt["centre"] - r_alt, -np.inf))
                hi_alt = np.minimum(hi, np.nextafter(alt["centre"] + r_alt, np.inf))
                if np.any(lo_alt > hi_alt):
                    problems.append("the two least-squares enclosures do not meet in "
                                    f"{[inertial.NAMES[k] for k in np.flatnonzero(lo_alt > hi_alt)]}")
                else:
                    lo, hi = lo_alt, hi_alt
        params = {"none": [], "mass": [0], "all": list(range(10))}[st.set_membership]
        if params and not problems:
            sm_lo, sm_hi, feasible = set_membership_bounds(self.rows, self.theta_r, self.theta_r_radius, st, lo, hi,
                                                           params)
            if not feasible:
                problems.append("the set-membership LP is infeasible")
            else:
                lo = np.where(np.isnan(sm_lo), lo, np.maximum(lo, sm_lo))
                hi = np.where(np.isnan(sm_hi), hi, np.minimum(hi, sm_hi))
        box_ok, lam = _box_is_consistent(centre, radius)
        at_centre = np.abs(sol.theta - centre) <= 1e-6 * (np.abs(centre) + radius + 1e-9)
        if box_ok:
            case = "interior"  # exact hull of θ*([m]); θ* linear in m on the whole box
        elif lam > 0 and np.all(at_centre):
            case = "interior_at_m"  # LMI inactive at m but reachable inside [m]; box encloses truth
        else:
            case = "lmi_active"  # θ0 near the LMI boundary; box around Y⁺U(m) still encloses truth
        # Intersect with the published interval (or the prior).
        old = (prev.lower, prev.upper) if prev is not None else self.prior
        new_lo, new_hi = (lo, hi) if old is None else (np.maximum(lo, old[0]), np.minimum(hi, old[1]))
        if np.any(new_lo > new_hi):
            problems.append("the new interval does not meet the published one in "
                            f"{[inertial.NAMES[k] for k in np.flatnonzero(new_lo > new_hi)]}")
        notes = []
        quad_ratio = float(np.max(self.rows.quad / np.maximum(_torque_row_radius(self.rows), 1e-300)))
        if quad_ratio > st.quadrature_warn_ratio:
            notes.append(f"quadrature term up to {quad_ratio:.2f} of a row's torque radius: the motion is not "
                         "resolved by the sampling")
        if problems:
            if self.consistent:
                notes.insert(0, "inconsistent data (" + "; ".join(problems) + "): torque noise or θ_r outside the "
                             "declared bounds, or the model is wrong; keeping the last consistent interval")
            self.consistent = False
        self.messages.extend(notes)
        if not self.consistent:  # latched: publish the last consistent box (or the prior) unchanged
            keep = prev or self._prior_estimate(np.inf, 0, "")
            theta_e, new_lo, new_hi = keep.theta_e.copy(), keep.lower.copy(), keep.upper.copy()
        else:
            self.eta = sol.eta  # the consistent least-squares solution stays the warm start
            # Publish the nominal clipped into the interval: the truth is inside it, so per parameter
            # the projection is never farther from the truth (it matters for barely excited inertias).
            theta_e = np.clip(sol.theta, new_lo, new_hi)
        theta = robot.theta.copy()
        theta[robot.ee_slice] = theta_e
        t_lo, t_hi = self._robot_box()
        t_lo[robot.ee_slice], t_hi[robot.ee_slice] = new_lo, new_hi
        est = Estimate(theta_e=theta_e, lower=new_lo, upper=new_hi, theta=theta, theta_lower=t_lo, theta_upper=t_hi,
                       eta=sol.eta, theta_ls=centre, update_lower=lo, update_upper=hi,
                       radius_torque=hull["rad_torque"], radius_theta_r=hull["rad_theta_r"],
                       radius_quadrature=hull["rad_quad"], radius_rounding=hull["rad_round"], case=case,
                       consistent=self.consistent, cond_Y=cond, num_segments=S, num_samples=self.num_samples,
                       solver={"name": sol.solver, "success": sol.success, "result": sol.message,
                               "cost": sol.cost, "grad_norm": sol.grad_norm, "newton_steps": sol.newton_steps},
                       message="; ".join(notes), problems=problems, quadrature_ratio=quad_ratio)
        return self._finish(est, start)

    def _finish(self, est, start):
        est.update_time_s = time.perf_counter() - start
        self.update_times_s.append(est.update_time_s)
        self.estimate = est
        return est

    def _robot_box(self):
        lo, hi = self.robot.theta.copy(), self.robot.theta.copy()
        mask = self.robot.rest_mask()
        lo[mask], hi[mask] = self.theta_r - self.theta_r_radius, self.theta_r + self.theta_r_radius
        return lo, hi

    def _prior_estimate(self, cond, S, message):
        prev = self.estimate
        if prev is not None and prev.case != "prior":
            prev.message = message
            return prev
        theta_e = self.prior_nominal.copy()
        lo, hi = self.prior if self.prior is not None else (np.full(10, -np.inf), np.full(10, np.inf))
        t_lo, t_hi = self._robot_box()
        t_lo[self.robot.ee_slice], t_hi[self.robot.ee_slice] = lo, hi
        theta = self.robot.theta.copy()
        theta[self.robot.ee_slice] = theta_e
        z = np.zeros(10)
        return Estimate(theta_e, lo.copy(), hi.copy(), theta, t_lo, t_hi, self.eta, theta_e, lo.copy(), hi.copy(),
                        z, z, z, z, "prior", self.consistent, cond, S, self.num_samples, {}, message)

    def prior_estimate(self):
        """What to publish before the first identification (nominal θ_e, prior box)."""
        return self._prior_estimate(np.inf, 0, "no data yet")


def identify(robot, t, q, v, tau, settings: EstimatorSettings | None = None, prior=None, prior_nominal=None):
    """Algorithm 1 on a whole log (pure function): returns an Estimate."""
    est = IncrementalEstimator(robot, settings, prior, prior_nominal)
    est.add(t, q, v, tau)
    return est.update()


# ---------------------------------------------------------------------------------------------
# Synthetic data (validation, benchmarks, Table V)
# ---------------------------------------------------------------------------------------------
def fourier_motion(rng, robot, duration_s, rate_hz, harmonics=5, period_s=None, centre=None,
                   velocity_fraction=0.7, position_amplitude_rad=0.6, t0=0.0):
    """Smooth random finite Fourier series (Swevers form) within joint position/velocity limits.

    q_j(t) = c_j + Σ_l a_jl/(lω) sin(lωt) − b_jl/(lω) cos(lωt), scaled on the sample grid.
    Returns (t, motion): the grid and motion(times) -> (q, v, a) at any times.
    """
    n = robot.n
    jp = robot.joint_params
    period = period_s or max(duration_s, 1.0)
    w = 2 * np.pi / period
    t = t0 + np.arange(int(round(duration_s * rate_hz)) + 1) / rate_hz
    a_c = rng.uniform(-1, 1, (n, harmonics))
    b_c = rng.uniform(-1, 1, (n, harmonics))
    ell = np.arange(1, harmonics + 1)

    def series(times):
        wt = np.outer(times, ell * w)  # (N, L)
        sin, cos = np.sin(wt), np.cos(wt)
        q_dev = (sin @ (a_c / (ell * w)).T) - (cos @ (b_c / (ell * w)).T)
        v = cos @ a_c.T + sin @ b_c.T
        acc = -(sin * (ell * w)) @ a_c.T + (cos * (ell * w)) @ b_c.T
        return q_dev, v, acc

    q_dev, v, _ = series(t)
    mean = q_dev.mean(0)
    # Scale per joint: velocity within the fraction of the limit, deviation within the amplitude.
    s_v = velocity_fraction * jp.velocity_limit / np.maximum(np.abs(v).max(0), 1e-9)
    s_q = position_amplitude_rad / np.maximum(np.abs(q_dev - mean).max(0), 1e-9)
    s = np.minimum(s_v, s_q)
    if centre is None:
        centre = np.zeros(n)
        finite = np.isfinite(jp.position_lower) & np.isfinite(jp.position_upper)
        centre[finite] = 0.5 * (jp.position_lower + jp.position_upper)[finite]
    centre = np.asarray(centre, float)

    def motion(times):
        q_dev, v, acc = series(np.atleast_1d(np.asarray(times, float)))
        return centre + (q_dev - mean) * s, v * s, acc * s

    q = motion(t)[0]
    if not (np.all(q >= jp.position_lower) and np.all(q <= jp.position_upper)):
        raise EstimatorError("trajectory leaves the joint limits; choose a centre inside them")
    return t, motion


def fourier_trajectory(rng, robot, duration_s, rate_hz, **kw):
    """`fourier_motion` sampled on its grid: t, q, v, a."""
    t, motion = fourier_motion(rng, robot, duration_s, rate_hz, **kw)
    return (t, *motion(t))


_GAUSS_NODES, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(3)


def held_torque(robot, motion, t, theta):
    """The torque a zero-order hold must apply on each step [t_k, t_k+1] to produce `motion`
    exactly, in the momentum sense: τ̄_k = (1/h_k) ∫ τ_ID dt (3-point Gauss, error ~h⁶; the last sample
    holds over one more step of the same length). Over any segment of whole steps
    ∫ τ_ID dt = Σ τ̄_k h_k, so (t, q, v, τ̄) is an exact held-torque log of the motion."""
    h = np.diff(t)
    h = np.append(h, h[-1])
    nodes = t[:, None] + 0.5 * h[:, None] * (1 + _GAUSS_NODES[None, :])  # (N, 4)
    q, v, a = motion(nodes.ravel())
    tau = robot.inverse_dynamics(q, v, a, theta).reshape(len(t), len(_GAUSS_NODES), -1)
    return 0.5 * np.tensordot(tau, _GAUSS_WEIGHTS, axes=([1], [0]))


def perturbed_robot_theta(rng, robot, ratio):
    """Rest-of-robot θ_r perturbed uniformly within ±ratio·|θ_r| (what [θ_r] allows)."""
    theta = robot.theta.copy()
    mask = robot.rest_mask()
    theta[mask] *= 1 + rng.uniform(-ratio, ratio, mask.sum())
    return theta


def simulate_log(rng, robot, theta_true, duration_s=7.5, rate_hz=1000.0, noise_ratio=0.025, noise_floor_Nm=0.05,
                 noise_scale=1.0, torque="held", **traj):
    """Joint log of an open-loop exciting motion with θ_true, plus uniform noise inside
    |τ_meas − τ| ≤ noise_scale·(ratio|τ| + floor). torque "held": τ is the zero-order-hold
    torque that produces the motion (`held_torque`, what a digital controller applies);
    "sampled": τ is inverse dynamics at the sample instants. Returns t, q, v, τ_meas, τ."""
    t, motion = fourier_motion(rng, robot, duration_s, rate_hz, **traj)
    q, v, a = motion(t)
    tau = held_torque(robot, motion, t, theta_true) if torque == "held" else robot.inverse_dynamics(q, v, a, theta_true)
    bound = noise_scale * (noise_ratio * np.abs(tau) + noise_floor_Nm)
    tau_meas = tau + rng.uniform(-1, 1, tau.shape) * bound
    return t, q, v, tau_meas, tau
