"""The Estimate Algorithm 1 publishes (incremental.IncrementalEstimator.update): θ_e, its box, the
update's own boxes and radii, and what its assumptions rest on."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.model import inertial

from .segments import SegmentRows


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
    # A5 (quadrature): "unverified" (assumed: the motion between the samples is unknown, e.g. a log
    # offline), "checked" (on every segment: `segments.resolved_quadrature`, or A5's bound is at
    # least the certificate from an acceleration bound on every step, `segments.certified_rows`),
    # "certified" (A5 not shown on some step: there the row carries the certificate instead, sound
    # without A5 given the acceleration bound), or "violated" (proven false on some segment, whose
    # bound was re-derived on sub-steps).
    quadrature_assumption: str = "unverified"
    update_time_s: float = 0.0
    # The data-driven box (data ∩ prior ∩ the previous data box) before physical pruning; equals
    # lower/upper when settings.physical_pruning is off.
    data_lower: np.ndarray | None = None
    data_upper: np.ndarray | None = None
    # The paper's first-order interval (Theorem 2 with the Jacobian at m only): Y⁺U(m) ± |Y⁺ ∂U/∂m|
    # rad([m]), unweighted rows, no quadrature or rounding term, no prior: reported, never used.
    first_order_lower: np.ndarray | None = None
    first_order_upper: np.ndarray | None = None

    @property
    def widths(self) -> np.ndarray:
        return self.upper - self.lower

    def contains(self, theta_e: ArrayLike, tol: float = 0.0) -> bool:
        return bool(np.all((self.lower - tol <= theta_e) & (theta_e <= self.upper + tol)))

    def to_json(self, names: Sequence[str] = inertial.NAMES) -> dict:
        f = lambda x: [float(v) for v in np.asarray(x).ravel()]  # noqa: E731
        return {
            "nominal": f(self.theta_e),
            "lower": f(self.lower),
            "upper": f(self.upper),
            "names": list(names),
            "widths": f(self.widths),
            "theta_ls": f(self.theta_ls),
            "update_lower": f(self.update_lower),
            "update_upper": f(self.update_upper),
            "radius": {
                "torque": f(self.radius_torque),
                "theta_r": f(self.radius_theta_r),
                "quadrature": f(self.radius_quadrature),
                "rounding": f(self.radius_rounding),
            },
            "case": self.case,
            "consistent": self.consistent,
            "cond_Y": float(self.cond_Y),
            "num_segments": int(self.num_segments),
            "num_samples": int(self.num_samples),
            "solver": self.solver,
            "message": self.message,
            "problems": list(self.problems),
            "quadrature_ratio": float(self.quadrature_ratio),
            "quadrature_assumption": self.quadrature_assumption,
            "update_time_s": float(self.update_time_s),
            "data_lower": f(self.lower if self.data_lower is None else self.data_lower),
            "data_upper": f(self.upper if self.data_upper is None else self.data_upper),
            "first_order_lower": None if self.first_order_lower is None else f(self.first_order_lower),
            "first_order_upper": None if self.first_order_upper is None else f(self.first_order_upper),
        }


def quadrature_assumption(rows: SegmentRows) -> str:
    """What A5 rests on for these rows: violated | checked | certified | unverified (see Estimate)."""
    if rows.a5_violated.any():
        return "violated"
    if not len(rows):
        return "unverified"
    if np.all(rows.a5_checked | rows.a5_shown):
        return "checked"
    return "certified" if np.all(rows.a5_checked | rows.a5_certified) else "unverified"
