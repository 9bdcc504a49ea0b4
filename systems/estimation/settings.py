"""Estimator settings (from a scenario's estimator and noise sections) and its error type."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING

import numpy as np
from safesysid.systems.config import ParameterFloors
from safesysid.systems.model.torque_noise import DeclaredTorqueNoise

if TYPE_CHECKING:
    from ..config import BoundingVolume as VolumeField
    from ..config import Scenario

EPS = np.finfo(float).eps


class EstimatorError(ValueError):
    """Bad estimator input (too little data, wrong shapes, non-finite values)."""


@dataclass(frozen=True)
class BoundingVolume:
    """A region containing the payload, in the end-effector frame: an ellipsoid (half_extent_m =
    semi-axes) or a box (half_extent_m = half side lengths), centred at centre_m, axes rotated by R."""

    shape: str
    centre_m: np.ndarray
    half_extent_m: np.ndarray
    R: np.ndarray

    def __post_init__(self):
        if self.shape not in ("ellipsoid", "box"):
            raise EstimatorError(f"payload.bounding_volume.shape: {self.shape!r} is not none, ellipsoid or box")
        if np.shape(self.centre_m) != (3,) or np.shape(self.half_extent_m) != (3,):
            raise EstimatorError("payload.bounding_volume: centre_m and half_extent_m need 3 entries")
        if not np.all(np.asarray(self.half_extent_m) > 0):
            raise EstimatorError("payload.bounding_volume.half_extent_m: every entry must be > 0")

    def forms(self) -> list[np.ndarray]:
        """The 4×4 Q with [x; 1]ᵀ Q [x; 1] ≥ 0 for every x of the volume (one per ellipsoid, three per box)."""
        c, a = np.asarray(self.centre_m, float), np.asarray(self.half_extent_m, float)
        if self.shape == "ellipsoid":
            shapes = [self.R @ np.diag(1.0 / a**2) @ self.R.T]
        else:
            shapes = [np.outer(self.R[:, i], self.R[:, i]) / a[i] ** 2 for i in range(3)]
        out = []
        for S in shapes:  # 1 − (x − c)ᵀ S (x − c)
            Q = np.zeros((4, 4))
            Q[:3, :3] = -S
            Q[:3, 3] = Q[3, :3] = S @ c
            Q[3, 3] = 1.0 - c @ S @ c
            out.append(Q)
        return out

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Which of the points (N, 3) lie in the volume (tests draw payloads inside it)."""
        local = (np.atleast_2d(points) - self.centre_m) @ self.R / self.half_extent_m
        if self.shape == "ellipsoid":
            return np.sum(local**2, 1) <= 1.0
        return np.all(np.abs(local) <= 1.0, 1)


def rpy_matrix(rpy: Sequence[float]) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def payload_volume(field: VolumeField) -> BoundingVolume | None:
    """The scenario's payload.bounding_volume as a physical.BoundingVolume (None for shape none)."""
    if field.shape == "none":
        return None
    return BoundingVolume(
        field.shape, np.array(field.centre_m, float), np.array(field.half_extent_m, float), rpy_matrix(field.rpy_rad)
    )


def lag_interval(value: float | Sequence[float]) -> tuple[float, float]:
    """(lo, hi) of a declared lag: one number d is [d, d]; EstimatorError unless 0 <= lo <= hi."""
    lo, hi = (value, value) if np.ndim(value) == 0 else tuple(value) if len(value) == 2 else (None, None)
    if lo is None or not (np.isfinite(lo) and np.isfinite(hi) and 0 <= lo <= hi):
        raise EstimatorError(f"estimator.torque_lag_s: {value!r} must be a number >= 0 or [lo, hi] with 0 <= lo <= hi")
    return float(lo), float(hi)


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
    # held: a step longer than 1.5 hold periods is a gap (samples were lost, their torque is
    # unknown). The default is the 1 kHz controller's step, so a lost sample is never integrated
    # as if held; None (no hold rule, only max_gap_s) must be asked for.
    hold_period_s: float | None = 0.001
    torque_rate_limit_Nm_s: float = 200.0  # continuous: declared |dτ/dt| of the applied torque
    # held: the sensor low-passes its reading with this first-order time constant (0: no lag),
    # or with one somewhere in [lo, hi]; each step's reading is recovered one sample late, exactly
    # for one value, enclosed over the interval for two (estimation/lag.py).
    torque_lag_s: float | tuple[float, float] = 0.0
    # held: step k's torque is the sample this much later (> 0: the reading arrives late; < 0: the
    # torque reaches the joint late), re-paired before the lag is undone (estimation/delay.py).
    torque_delay_s: float = 0.0
    solver: str = "ipopt"  # ipopt | snopt
    declared_noise: DeclaredTorqueNoise = field(default_factory=DeclaredTorqueNoise)  # |τ_meas − τ| ≤ ratio·|τ| + floor
    theta_r_ratio: float = 0.05  # [θ_r] = θ_r ± max(ratio·|θ_r|, floor of its kind)
    theta_r_floor: ParameterFloors = field(default_factory=ParameterFloors)
    # κ of the quadrature bound (`quadrature_bound`, its assumption); ≥ 2 covers any integrand
    # that is monotone on each step, whatever its slope.
    quadrature_safety: float = 2.0
    # Above this share of a row's torque radius the quadrature term is reported as "motion not
    # resolved by the sampling" (an event; the bound still holds under its assumption).
    quadrature_warn_ratio: float = 1.0
    # |q̈_j| between the samples never exceeds this (rad/s², one value or one per joint; None: not
    # known): each step's quadrature term is then certified without A5 and A5 checked against it
    # (estimation/quadrature_certificate.py); samples that contradict it latch `consistent` off.
    acceleration_bound_rad_s2: float | tuple[float, ...] | None = None
    # Derive that bound instead, per step, from the model's dynamics under the held torque with θ in
    # the estimator's own box (estimation/acceleration_bound.py); needs a held torque and no declared bound.
    derive_acceleration_bound: bool = False
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
    # > 0: the LP takes only the segments of the last this many seconds, inside the published data
    # box (which the older segments already bound): an update's cost stops growing with the data
    # (`IncrementalEstimator._update_box`). 0: every segment.
    set_membership_window_s: float = 0.0
    # Point estimate θ0: "map" (θ_r marginalised with its box as prior, rows whitened) or
    # "paper" (the paper's ‖Y P(η) − U‖², rows scaled per `row_weighting`); see _left_inverse.
    point_estimate: str = "map"
    # Prior physical knowledge (estimation/physical.py): prune the published box with J(θ_e) ⪰ 0
    # and, given a volume containing the payload, its density-realizability LMI. The data-driven
    # box is reported separately (Estimate.data_lower/upper).
    physical_pruning: bool = False
    payload_volume: BoundingVolume | None = None

    @classmethod
    def from_scenario(cls, s: Scenario) -> EstimatorSettings:
        """The scenario's estimator section (every field of it, by name), its declared noise and
        parameter box (noise), hold period (default: the plant's step) and payload volume."""
        e = s.estimator
        own = {f.name: getattr(e, f.name) for f in fields(e)}
        return cls(
            **own
            | {
                "hold_period_s": e.hold_period_s or s.plant.time_step_s,
                "acceleration_bound_rad_s2": tuple(e.acceleration_bound_rad_s2) or None,
                "declared_noise": DeclaredTorqueNoise.from_noise(s.noise),
                "theta_r_ratio": s.noise.theta_r_ratio,
                "theta_r_floor": s.noise.theta_r_floor,
                "payload_volume": payload_volume(s.payload.bounding_volume),
            }
        )

    def segment_gap_s(self) -> float:
        """Longest step a segment may span: max_gap_s, and for a held torque 1.5 hold periods
        (a longer step lost held samples whose torque is unknown)."""
        if self.torque_signal == "held" and self.hold_period_s:
            return min(self.max_gap_s, 1.5 * self.hold_period_s)
        return self.max_gap_s

    def lag_interval(self) -> tuple[float, float]:
        """The declared torque lag as (lo, hi) (lo == hi for one value; (0, 0): no lag)."""
        return lag_interval(self.torque_lag_s)

    def torque_rule(self) -> str:
        """Quadrature of ∫τ dt: the exact left sum of a held torque, else the trapezoid."""
        return "euler" if self.torque_signal == "held" else "trapezoid"
