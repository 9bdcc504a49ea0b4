"""Segments of a joint log and their rows: the integrated momentum-rate regressor (∫W_c dt
per segment without forming W_c per sample), its quadrature bound, and Y, D_r, ∫τ with the
declared error bound of each row.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.math.spatial import cross
from safesysid.systems.model import regressors

from .settings import EstimatorError, EstimatorSettings

# The motion between samples, when known: times -> (q, v, a) (A5 is then checked).
Reference = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]

if TYPE_CHECKING:
    from safesysid.systems.model.regressors import KinematicTree
    from safesysid.systems.model.robot_model import RobotModel


def segment_bounds(t: ArrayLike, horizon_s: float, max_gap_s: float) -> tuple[np.ndarray, int]:
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
        tt = t[r0 : r1 + 1]
        while True:
            k = np.searchsorted(tt, t[a] + horizon_s - 1e-12 * max(1.0, abs(t[a])), side="left") + r0
            if k > r1:
                break
            out.append((a, k))
            a = k
        next_start = a
    return np.asarray(out, int).reshape(-1, 2), int(next_start)


def sample_weights(t: np.ndarray, a: int, b: int, *, integration: str) -> np.ndarray:
    """Quadrature weights of samples a..b for ∫ over [t_a, t_b]."""
    dt = np.diff(t[a : b + 1])
    w = np.zeros(b - a + 1)
    if integration == "euler":  # paper: left Riemann sum
        w[:-1] = dt
    else:
        w[:-1] += 0.5 * dt
        w[1:] += 0.5 * dt
    return w


def _inertia_basis():
    """(6, 6, 10) K with s^T K(x) = Σ_ab s_a x_b K[a, b, :] (K(x) θ = I(θ) x is linear in x)."""
    return np.stack([regressors.inertia_times(np.eye(6)[b])[:, :] for b in range(6)], 1)


_K_BASIS = _inertia_basis()


def _to_body(R, p, x):
    """Motion vectors about the world origin (N, k, 6) -> body frame at (R (N,3,3), p (N,3)):
    spatial.to_body for k vectors per pose, as one matrix product per pose (faster here)."""
    k = x.shape[1]
    w = x[..., :3]
    both = np.concatenate([w, x[..., 3:] + cross(w, p[:, None, :])], 1) @ R  # rows times R = Rᵀ·
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
        both = _to_body(
            kin.R[:, i],
            kin.p[:, i],
            np.concatenate(
                [kin.Sdot[:, js], kin.S[:, js], kin.V[:, i, None], np.broadcast_to(g_world, (nsamp, 1, 6))], 1
            ),
        )
        joints.append(js)
        screws.append(np.concatenate([both[:, :k], both[:, k : 2 * k]], 0))
        twist_grav.append(np.concatenate([both[:, 2 * k], both[:, 2 * k + 1]], 0))
    return _Factors(joints, screws, twist_grav, nsamp)


def integrated_rate_regressor(
    tree: KinematicTree,
    q: np.ndarray,
    v: np.ndarray,
    t: np.ndarray,
    bounds: np.ndarray,
    *,
    integration: str = "trapezoid",
    factors: _Factors | None = None,
) -> np.ndarray:
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
    weights = [sample_weights(t, a, b, integration=integration) for a, b in bounds]
    for i in range(n):
        js = factors.joints[i]
        k = len(js)
        sT = factors.screws[i].transpose(1, 2, 0).reshape(k * 6, 2 * N)  # (k·6, 2N)
        x = factors.twist_grav[i]
        gram = np.empty((len(bounds), k * 6, 6))
        for s, (a, b) in enumerate(bounds):
            idx = np.r_[a : b + 1, N + a : N + b + 1]
            ww = np.concatenate([weights[s], weights[s]])
            gram[s] = sT[:, idx] @ (x[idx] * ww[:, None])
        out[:, js, 10 * i : 10 * i + 10] = gram.reshape(len(bounds), k, 36) @ kbasis
    return out


def segment_sums(values: np.ndarray, t: np.ndarray, bounds: np.ndarray, *, integration: str) -> np.ndarray:
    """∫ values dt per segment with the same quadrature, values (N, ...) -> (S, ...)."""
    out = np.empty((len(bounds),) + values.shape[1:])
    for s, (a, b) in enumerate(bounds):
        out[s] = np.tensordot(sample_weights(t, a, b, integration=integration), values[a : b + 1], 1)
    return out


def _rate_blocks(factors, n):
    """Per body i: (i, its ancestor joints, W_c,rigid[:, joints, body i] at every sample (N, k, 10)),
    from Σ_ab s_a x_b K_ab = s · (x K), x K one (2N, 6)(6, 60) product per body."""
    N = factors.nsamp
    k_by_b = _K_BASIS.transpose(1, 0, 2).reshape(6, 60)  # (b, a·10)
    for i in range(n):
        s, xk = factors.screws[i], (factors.twist_grav[i] @ k_by_b).reshape(2 * N, 6, 10)
        yield i, factors.joints[i], s[:N] @ xk[:N] + s[N:] @ xk[N:]


def rate_regressor_samples(factors: _Factors, n: int) -> np.ndarray:
    """W_c,rigid at every sample (N, n, 10 n): the per-sample form of `integrated_rate_regressor`."""
    out = np.zeros((factors.nsamp, n, 10 * n))
    for i, joints, block in _rate_blocks(factors, n):
        out[:, joints, 10 * i : 10 * i + 10] = block
    return out


def integrand_rates(
    t: np.ndarray, factors: _Factors, fric_cols: np.ndarray, theta_centre: np.ndarray, theta_radius: np.ndarray
) -> np.ndarray:
    """Per step k and joint, a_k ≥ |f(t_k+1) − f(t_k)| / h_k for the integrand f = W_c θ and
    EVERY θ in θ_centre ± θ_radius (the mean of ḟ over the step), (N − 1, n). W_c = rigid part
    (from the factors, body by body: never the whole (N, n, 14 n) array) + fric_cols (N, n, 4 n)."""
    n = fric_cols.shape[1]
    f = fric_cols @ theta_centre[10 * n :]
    spread = np.abs(np.diff(fric_cols, axis=0)) @ theta_radius[10 * n :]
    for i, joints, block in _rate_blocks(factors, n):
        body = slice(10 * i, 10 * i + 10)
        f[:, joints] += block @ theta_centre[body]
        spread[:, joints] += np.abs(np.diff(block, axis=0)) @ theta_radius[body]
    return (np.abs(np.diff(f, axis=0)) + spread) / np.diff(t)[:, None]


def quadrature_bound(
    t: np.ndarray, rates: np.ndarray, bounds: np.ndarray, *, integration: str, safety: float
) -> np.ndarray:
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
        out[s] = c * safety * (h2[a:b] @ neighbour_max(rates[a:b]))
    return out


def neighbour_max(r: np.ndarray) -> np.ndarray:
    """max(a_k−1, a_k, a_k+1) over the steps of one segment (independent of how data was chunked)."""
    local = r.copy()
    local[1:] = np.maximum(local[1:], r[:-1])
    local[:-1] = np.maximum(local[:-1], r[1:])
    return local


def _integrand_on(robot, reference, t, bounds, integration, theta_box):
    """(∫W_c dt per segment by the quadrature on the grid t (S, n, 14 n), the integrand's mean
    rates per step `integrand_rates` (N − 1, n)) of the motion `reference` sampled at t."""
    q, v, _ = reference(t)
    factors = _pair_factors(robot.tree, q, v)
    fric = regressors.friction_columns(v, kind="rate", smoothing_velocity=robot.coulomb_smoothing)
    wc = np.concatenate(
        [
            integrated_rate_regressor(robot.tree, q, v, t, bounds, integration=integration, factors=factors),
            segment_sums(fric, t, bounds, integration=integration),
        ],
        -1,
    )
    return wc, integrand_rates(t, factors, fric, *theta_box)


def resolved_quadrature(
    robot: RobotModel,
    reference: Reference,
    t: np.ndarray,
    bounds: np.ndarray,
    settings: EstimatorSettings,
    theta_box: tuple[np.ndarray, np.ndarray],
    *,
    substeps: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """A5 checked where the motion between the samples is known (`reference(times) -> (q, v, a)`,
    the motion the samples are of; online the commanded plan): per segment (bound (S, n),
    violated (S,) bool).

    violated: on some step the largest mean rate of the integrand over one of `substeps` equal
    sub-steps (each a LOWER bound of sup |ḟ| on the step) exceeds κ·max(a_k−1, a_k, a_k+1), A5's
    premise: A5 is then false on that step (a proof, no false alarm). bound: the error of the
    samples' quadrature, the exact difference between it and the sub-step quadrature (over every θ
    in theta_box) plus the sub-step quadrature's own A5 bound, i.e. A5 needed only on sub-steps
    `substeps` times shorter."""
    h = np.diff(t)
    fine_t = np.append((t[:-1, None] + h[:, None] * (np.arange(substeps) / substeps)).ravel(), t[-1])
    coarse, rates = _integrand_on(robot, reference, t, bounds, settings.integration, theta_box)
    fine, fine_rates = _integrand_on(robot, reference, fine_t, bounds * substeps, settings.integration, theta_box)
    diff = coarse - fine
    bound = np.abs(diff @ theta_box[0]) + np.abs(diff) @ theta_box[1]
    bound += quadrature_bound(
        fine_t, fine_rates, bounds * substeps, integration=settings.integration, safety=settings.quadrature_safety
    )
    sub_max = fine_rates.reshape(len(h), substeps, -1).max(1)
    violated = np.array(
        [np.any(sub_max[a:b] > settings.quadrature_safety * neighbour_max(rates[a:b])) for a, b in bounds], bool
    )
    return bound, violated


def torque_rate_bound(
    t: np.ndarray, tau_meas: np.ndarray, radius: np.ndarray, *, bounds: np.ndarray, rate_limit: float
) -> tuple[np.ndarray, np.ndarray]:
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
    # (S,) bool: A5 checked on the motion between the samples (`resolved_quadrature`), and found false
    a5_checked: np.ndarray | None = None
    a5_violated: np.ndarray | None = None
    # (S,) bool: the quadrature certified from an acceleration bound (quadrature_certificate.py
    # `certify_rows`); A5's own
    # bound shown to hold on every step (it is >= the certificate); the samples contradict the bound
    a5_certified: np.ndarray | None = None
    a5_shown: np.ndarray | None = None
    accel_violated: np.ndarray | None = None

    def __post_init__(self):
        for name in ("a5_checked", "a5_violated", "a5_certified", "a5_shown", "accel_violated"):
            if getattr(self, name) is None:
                setattr(self, name, np.zeros(len(self.t0), bool))

    @classmethod
    def empty(cls, n: int, nr: int) -> SegmentRows:
        z = lambda *s: np.zeros(s)  # noqa: E731
        return cls(
            z(0),
            z(0),
            z(0, n, 10),
            z(0, n, nr),
            z(0, n),
            z(0),
            z(0),
            z(0, n),
            z(0, n),
            z(0, n),
            z(0, n),
            np.zeros(0, bool),
            z(0, n),
            np.zeros(0, bool),
            np.zeros(0, int),
            np.zeros(0, int),
        )

    def __len__(self):
        return len(self.t0)

    def concat(self, other: SegmentRows) -> SegmentRows:
        vals = {k: np.concatenate([getattr(self, k), getattr(other, k)]) for k in self.__dataclass_fields__}
        return SegmentRows(**vals)

    def since(self, t_s: float) -> SegmentRows:
        """The segments that end after t_s."""
        keep = self.t1 > t_s
        return SegmentRows(**{k: getattr(self, k)[keep] for k in self.__dataclass_fields__})


def torque_radius(
    tau_meas: np.ndarray, settings: EstimatorSettings, reading_radius: np.ndarray | None = None
) -> np.ndarray:
    """Per-sample bound on |τ_true − τ_meas| from the declared |r − τ| ≤ ratio|τ| + floor of the
    sensor's reading r. reading_radius ρ: τ_meas is only known to be within ρ of r (a lag
    interval, estimation/lag.py), so |τ| ≤ (|τ_meas| + ρ + floor)/(1 − ratio) and the bound is
    (ratio (|τ_meas| + ρ) + floor)/(1 − ratio) + ρ (ρ = 0: the plain bound, bit for bit)."""
    if settings.declared_noise.ratio >= 1:
        raise EstimatorError("noise.declared_torque_ratio must be < 1")
    return settings.declared_noise.bound_from_measured(tau_meas, reading_radius)


def build_segment_rows(
    robot: RobotModel,
    t: np.ndarray,
    q: np.ndarray,
    v: np.ndarray,
    tau: np.ndarray,
    bounds: np.ndarray,
    settings: EstimatorSettings,
    *,
    theta_box: tuple[np.ndarray, np.ndarray] | None = None,
    index_offset: int = 0,
    reading_radius: np.ndarray | None = None,
    reference: Reference | None = None,
) -> SegmentRows:
    """Y, D_r, ∫τ and interval bookkeeping for the given segments (vectorized over samples).

    theta_box: (centre, radius) over all 14 n parameters, the box the true θ lies in, for the
    quadrature bound (None: the model's θ, zero radius). reading_radius (N, n): how far each τ is
    from the sensor's reading (a lag interval; `torque_radius`). reference: the motion between
    the samples, times -> (q, v, a), when known: A5 is then checked (`resolved_quadrature`).
    """
    n = robot.n
    ee = robot.ee_slice
    rest = robot.rest_mask()
    S = len(bounds)
    if S == 0:
        return SegmentRows.empty(n, int(rest.sum()))
    lo, hi = int(bounds[:, 0].min()), int(bounds[:, 1].max())
    loc = bounds - lo
    tt, qq, vv, ta = t[lo : hi + 1], q[lo : hi + 1], v[lo : hi + 1], tau[lo : hi + 1]
    integ = settings.integration
    factors = _pair_factors(robot.tree, qq, vv)
    rate_fric = regressors.friction_columns(vv, kind="rate", smoothing_velocity=robot.coulomb_smoothing)
    D = _momentum_differences(robot, (tt, qq, vv), loc, integ=integ, factors=factors, rate_fric=rate_fric)
    rule = settings.torque_rule()
    T = segment_sums(ta, tt, loc, integration=rule)
    r = torque_radius(ta, settings, None if reading_radius is None else reading_radius[lo : hi + 1])
    w_first, w_last, r_inner, r_inner_sq = _radius_weights(tt, r, loc, rule)
    shared_prev = np.zeros(S, bool)
    shared_prev[1:] = loc[1:, 0] == loc[:-1, 1]
    centre, radius = (robot.theta, np.zeros_like(robot.theta)) if theta_box is None else theta_box
    rates = integrand_rates(tt, factors, rate_fric, centre, radius)
    quad = quadrature_bound(tt, rates, loc, integration=integ, safety=settings.quadrature_safety)
    violated = np.zeros(S, bool)
    a5_violated = np.zeros(S, bool)
    if reference is not None:  # never below the samples' own A5 bound
        resolved, a5_violated = resolved_quadrature(robot, reference, tt, loc, settings, (centre, radius))
        quad = np.maximum(quad, resolved)
    if settings.torque_signal == "continuous":
        err, violated = torque_rate_bound(tt, ta, r, bounds=loc, rate_limit=settings.torque_rate_limit_Nm_s)
        quad = quad + err
    return SegmentRows(
        t0=tt[loc[:, 0]],
        t1=tt[loc[:, 1]],
        Y=D[..., ee],
        D_r=D[..., rest],
        T=T,
        w_first=w_first,
        w_last=w_last,
        r_first=r[loc[:, 0]],
        r_last=r[loc[:, 1]],
        r_inner=r_inner,
        r_inner_sq=r_inner_sq,
        shared_prev=shared_prev,
        quad=quad,
        violated=violated,
        start_index=bounds[:, 0] + index_offset,
        end_index=bounds[:, 1] + index_offset,
        a5_checked=np.full(S, reference is not None),
        a5_violated=a5_violated,
    )


def _momentum_differences(robot, samples, loc, *, integ, factors, rate_fric):
    """D (S, n, 14 n) per segment: the momentum regressor's change minus the integrated rate
    regressor (rigid and friction columns), for the samples (t, q, v) and segment bounds loc."""
    tt, qq, vv = samples
    wc_rigid = integrated_rate_regressor(robot.tree, qq, vv, tt, loc, integration=integ, factors=factors)
    wc_fric = segment_sums(rate_fric, tt, loc, integration=integ)
    ends = np.unique(loc.ravel())
    wm = robot.momentum_regressor(qq[ends], vv[ends])
    pos = {k: r for r, k in enumerate(ends)}
    wm_a = wm[[pos[a] for a in loc[:, 0]]]
    wm_b = wm[[pos[b] for b in loc[:, 1]]]
    return wm_b - wm_a - np.concatenate([wc_rigid, wc_fric], -1)


def _radius_weights(tt, r, loc, rule):
    """Per segment: the torque rule's first and last sample weights and the weighted sums of the
    inner samples' radii and squared radii, (w_first, w_last, r_inner, r_inner_sq)."""
    S, n = len(loc), r.shape[1]
    w_first = np.empty(S)
    w_last = np.empty(S)
    r_inner = np.empty((S, n))
    r_inner_sq = np.empty((S, n))
    for s, (a, b) in enumerate(loc):
        w = sample_weights(tt, a, b, integration=rule)
        w_first[s], w_last[s] = w[0], w[-1]
        r_inner[s] = w[1:-1] @ r[a + 1 : b]
        r_inner_sq[s] = w[1:-1] ** 2 @ r[a + 1 : b] ** 2
    return w_first, w_last, r_inner, r_inner_sq
