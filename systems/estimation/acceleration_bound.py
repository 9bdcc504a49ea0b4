"""The joint-acceleration bound of the quadrature certificate derived online from the dynamics under
the held torque, per sample step (docs/guarantees.md §5 "A5 certified from the dynamics").

On a step [t_k, t_k+1] the applied torque u is held (zero-order hold; |u − τ_k| ≤ r_k, A3) and the
model's dynamics hold with the true θ in the estimator's box [θ] (friction and armature included):
    M(q; θ) q̈ = u − h(q, q̇; θ),   h = W_p(q, q̇, q̇, 0) θ = C q̇ + g + Fc tanh(q̇/vs) + Fv q̇ + β.
M = M_rigid + diag(Ia) with M_rigid ⪰ 0 (real bodies) and Ia ≥ Ia_lower > 0 (the box), so
M ⪰ D = diag(Ia_lower), M⁻¹ ⪯ D⁻¹ and, by Cauchy–Schwarz in the M⁻¹ inner product,
    |q̈_j| = |e_jᵀ M⁻¹ ρ| ≤ √(e_jᵀ M⁻¹ e_j · ρᵀ M⁻¹ ρ) ≤ √(Σ_k ρ_k² / Ia_k) / √Ia_j   (`from_residual`)
for |u − h|_k ≤ ρ_k, bounded over a box of states by the planner's interval passivity regressor
(`residual_bound`). The box is the forward one of the step under a candidate bound A (`forward_box`:
q̇ ∈ q̇_k ± A h, q − q_k ∈ hull(0, h·[q̇])); if the derived bound D over it is below A on every joint,
then |q̈| ≤ D on the whole step (continuation: while |q̈| ≤ A the state stays in the box, where the
dynamics give |q̈| ≤ D < A, and q̈ is continuous in time for a smooth Coulomb law, so the first
instant the bound could fail does not exist). A step where no candidate passes is left unbounded (inf).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from safesysid.systems.math.intervals import Interval, _down, _up, dot_rounding
from safesysid.systems.planner.interval_dynamics import interval_passivity_regressor

from .quadrature_certificate import certify_rows
from .settings import EstimatorError

if TYPE_CHECKING:
    from safesysid.systems.model.robot_model import RobotModel

    from .segments import Reference, SegmentRows
    from .settings import EstimatorSettings

_REL = 1e-12  # ≫ the (n + 4) units of roundoff of √(Σ ρ²/Ia / Ia_j) (all terms nonnegative)


def armature_lower(robot: RobotModel, theta_box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Ia_lower (n,) of the box (centre, radius); EstimatorError unless every one is > 0 (M ⪰ diag(Ia)
    then bounds M⁻¹)."""
    n = robot.n
    idx = 10 * n + 4 * np.arange(n) + 2
    centre, radius = (np.asarray(x, float)[idx] for x in theta_box)
    ia = _down(centre - radius)
    if not np.all(ia > 0):
        raise EstimatorError(f"a derived acceleration bound needs every armature's lower bound > 0, got {ia}")
    return ia


def from_residual(rho: np.ndarray, ia: np.ndarray) -> np.ndarray:
    """|q̈_j| ≤ √(Σ_k ρ_k²/Ia_k)/√Ia_j (…, n) for |M q̈| ≤ ρ componentwise and M ⪰ diag(Ia)."""
    energy = np.sum(rho**2 / ia, -1, keepdims=True)
    return _up(np.sqrt(energy / ia) * (1 + _REL))


def residual_bound(
    robot: RobotModel,
    q: Interval,
    v: Interval,
    tau: np.ndarray,
    torque_radius: np.ndarray,
    theta_box: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """ρ (N, n) ≥ |u − h(q, q̇; θ)| for every state in the boxes q, v (N, n), every u within
    torque_radius of tau and every θ in theta_box = (centre, radius): with [W] the interval passivity
    regressor W_p(q, q̇, q̇, 0) over the box, |τ − W_mid θ_c| + r + W_rad |θ_c| + |W| θ_rad."""
    w = interval_passivity_regressor(robot, q, v, v, Interval(np.zeros(q.shape)))
    centre, radius = (np.asarray(x, float) for x in theta_box)
    mid, mag = w.mid, w.mag
    point = mid @ centre
    spread = w.rad @ np.abs(centre) + mag @ radius
    err = dot_rounding(2 * w.shape[-1] + 3) * (
        np.abs(tau) + np.abs(mid) @ np.abs(centre) + 2 * mag @ (np.abs(centre) + radius)
    )
    return _up(np.abs(tau - point) + torque_radius + spread + err + dot_rounding(4) * torque_radius)


def forward_box(h: np.ndarray, q0: np.ndarray, v0: np.ndarray, accel: np.ndarray) -> tuple[Interval, Interval]:
    """Boxes (N, n) holding the state on steps of lengths h (N,) from (q0, v0) (N, n) while |q̈| ≤
    accel (N, n): q̇ ∈ q̇_0 ± A h and q − q_0 = ∫q̇ ∈ s·[q̇] ⊂ hull(0, h·[q̇]), outward."""
    h = np.asarray(h, float)[:, None]
    reach = _up(accel * h * (1 + dot_rounding(1)))
    v_lo, v_hi = _down(v0 - reach), _up(v0 + reach)
    move_lo, move_hi = np.minimum(0.0, h * v_lo), np.maximum(0.0, h * v_hi)
    pad = dot_rounding(3) * (np.abs(q0) + h * np.maximum(np.abs(v_lo), np.abs(v_hi)))
    return Interval(_down(q0 + move_lo - pad), _up(q0 + move_hi + pad)), Interval(v_lo, v_hi)


def derived_acceleration_bound(
    robot: RobotModel,
    samples: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    torque_radius: np.ndarray,
    theta_box: tuple[np.ndarray, np.ndarray],
    *,
    margin: float = 1.25,
    tries: int = 3,
) -> np.ndarray:
    """Per step of samples = (t, q, v, τ) (N each; τ_k held over step k), a bound (N − 1, n) on |q̈_j|
    over the step under the model's dynamics with θ in theta_box (module docstring); inf on a step
    where no candidate passed. Candidate: margin × the bound at the step's first sample, then
    doubled (`tries` in all)."""
    t, q, v, tau = (np.asarray(x, float) for x in samples)
    if robot.coulomb_smoothing <= 0:
        raise EstimatorError("a derived acceleration bound needs a smooth Coulomb law (coulomb_smoothing > 0)")
    ia = armature_lower(robot, theta_box)
    radius = np.broadcast_to(torque_radius, tau.shape)[:-1]
    centre, spread = (np.asarray(x, float) for x in theta_box)
    w = robot.passivity_regressor(q[:-1], v[:-1], v[:-1], np.zeros_like(v[:-1]))  # a candidate only
    rho0 = np.abs(tau[:-1] - w @ centre) + radius + np.abs(w) @ spread
    cand = margin * from_residual(rho0, ia) + 1e-9
    h = np.diff(t)
    bound = np.full(cand.shape, np.inf)
    todo = np.arange(len(cand))
    for _ in range(tries):
        if not len(todo):
            break
        qb, vb = forward_box(h[todo], q[todo], v[todo], cand[todo])
        derived = from_residual(residual_bound(robot, qb, vb, tau[todo], radius[todo], theta_box), ia)
        ok = np.all(derived < cand[todo], 1)
        bound[todo[ok]] = derived[ok]
        cand[todo[~ok]] = 2 * np.maximum(cand[todo[~ok]], derived[~ok])
        todo = todo[~ok]
    return bound


def exceeded_by(reference: Reference, t: np.ndarray, accel: np.ndarray, *, points: int = 8) -> np.ndarray:
    """(N − 1,) bool: the known motion between the samples, reference(times) → (q, q̇, q̈), exceeds
    accel (N − 1, n) at one of `points` instants of the step (its ends included)."""
    h = np.diff(t)
    times = t[:-1, None] + h[:, None] * np.linspace(0.0, 1.0, points)[None, :]
    _, _, a = reference(times.ravel())
    a = np.abs(np.asarray(a, float)).reshape(len(h), points, -1)
    return np.any(a > np.asarray(accel, float)[:, None, :], (1, 2))


def certify_segments(
    rows: SegmentRows,
    robot: RobotModel,
    settings: EstimatorSettings,
    samples: tuple[np.ndarray, ...],
    bounds: np.ndarray,
    *,
    theta_box: tuple[np.ndarray, np.ndarray],
    declared: np.ndarray | float | None,
    reference: Reference | None,
) -> SegmentRows:
    """The rows of the segments `bounds` of samples = (t, q, v, τ, reading radius) certified by
    `quadrature_certificate.certify_rows` from the declared acceleration bound, or from one derived per
    step of the samples' range with the declared torque radius and θ in theta_box (the rows unchanged
    when neither); with a reference, the steps whose known motion exceeds the bound are flagged."""
    lo, hi = int(bounds[:, 0].min()), int(bounds[:, 1].max())
    t, q, v, tau, rho = (np.asarray(x)[lo : hi + 1] for x in samples)
    accel = declared
    if settings.derive_acceleration_bound:
        radius = settings.declared_noise.bound_from_measured(tau, rho if rho.any() else None)
        accel = derived_acceleration_bound(robot, (t, q, v, tau), radius, theta_box)
    if accel is None:
        return rows
    accel = np.broadcast_to(np.asarray(accel, float), (hi - lo, robot.n))
    exceeded = None if reference is None else exceeded_by(reference, t, accel)
    return certify_rows(
        rows, robot, (t, q, v), bounds - lo, settings, theta_box=theta_box, accel=accel, exceeded=exceeded
    )
