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
intersected, then the prior (the truth is in it by assumption: no reported interval is ever wider
than the prior); then an optional certified LP (`set_membership_bounds`, exact projection of the
feasible polytope, dual-certified) tightens the mass (default) or all parameters. Each update
is intersected with the previous data-driven interval (or the prior): `data_lower/upper`.
Optionally (`physical_pruning`, module physical) that box is pruned with J(θ_e) ⪰ 0 and the
density-realizability LMI of a payload inside a bounding volume, by certified cutting-plane LPs
(an outer bound of the SDP), and intersected with the published interval. The paper's own
first-order interval (Jacobian at m only, no quadrature term) is reported next to ours. Any empty
set — the two boxes, the LP's polytope, the intersection, the pruning LP, a torque faster than
declared — is evidence that a declared bound failed: consistency is latched off and the last
consistent box is published unchanged (never the gap between boxes, never wider than before, never outside the prior).

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
             With a declared acceleration bound each step's term is the larger of that and a
             certificate resting on the bound alone (quadrature_certificate.py).
    rounding: L is a left inverse only up to E = LY − I: |E|(|centre| + radius) plus a relative
             pad for the float sums, then one ulp outward.
Segments are cut by time (horizon_s) and never span a step longer than max_gap_s (for a held
torque, nor 1.5 hold periods: a lost sample's held torque is unknown).

Modules: settings (EstimatorSettings, EstimatorError), segments (segmentation, integrated
regressor, quadrature bound, rows), log_cholesky (the NLP), enclosure (the interval),
incremental (Algorithm 1 chunk by chunk), physical (LMI pruning with prior physical knowledge),
synthetic (joint logs for tests and benchmarks).
"""

from .enclosure import (
    box_is_consistent,
    certified_lp_min,
    interval_hull,
    row_bounds,
    set_membership_bounds,
    torque_row_radius,
)
from .estimate import Estimate
from .incremental import IncrementalEstimator, identify
from .log_cholesky import (
    ETA_LOWER,
    ETA_UPPER,
    SolveResult,
    cost_and_gradient,
    cost_grad_hess,
    ift_sensitivity,
    ls_cost_terms,
    nearest_consistent,
    solve_log_cholesky,
)
from .physical import prune_box
from .segments import (
    SegmentRows,
    build_segment_rows,
    integrand_rates,
    integrated_rate_regressor,
    quadrature_bound,
    rate_regressor_samples,
    sample_weights,
    segment_bounds,
    segment_sums,
    torque_radius,
    torque_rate_bound,
)
from .settings import EPS, BoundingVolume, EstimatorError, EstimatorSettings
from .synthetic import fourier_motion, fourier_trajectory, held_torque, perturbed_robot_theta, simulate_log

__all__ = [
    "BoundingVolume",
    "EPS",
    "ETA_LOWER",
    "ETA_UPPER",
    "Estimate",
    "EstimatorError",
    "EstimatorSettings",
    "IncrementalEstimator",
    "SegmentRows",
    "SolveResult",
    "box_is_consistent",
    "build_segment_rows",
    "certified_lp_min",
    "cost_and_gradient",
    "cost_grad_hess",
    "fourier_motion",
    "fourier_trajectory",
    "held_torque",
    "identify",
    "ift_sensitivity",
    "integrand_rates",
    "integrated_rate_regressor",
    "interval_hull",
    "ls_cost_terms",
    "nearest_consistent",
    "perturbed_robot_theta",
    "prune_box",
    "quadrature_bound",
    "rate_regressor_samples",
    "row_bounds",
    "sample_weights",
    "segment_bounds",
    "segment_sums",
    "set_membership_bounds",
    "simulate_log",
    "solve_log_cholesky",
    "torque_radius",
    "torque_rate_bound",
    "torque_row_radius",
]
