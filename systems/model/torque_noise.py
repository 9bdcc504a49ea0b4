"""The declared torque-noise bound, one name and one formula for every consumer (the estimator's
rows, the planner's row weights): |τ_meas − τ| ≤ ratio·|τ| + floor per sample and joint.

The scenario declares it as noise.declared_torque_ratio / noise.declared_torque_floor_Nm; the
noise the simulated sensor draws is noise.torque_ratio / torque_floor_Nm (the truth, which a
scenario may set apart from the declaration to test it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.config import Noise


@dataclass(frozen=True)
class DeclaredTorqueNoise:
    ratio: float = 0.025
    floor_Nm: float = 0.05

    @classmethod
    def from_noise(cls, noise: Noise) -> DeclaredTorqueNoise:
        """The declaration of a scenario's noise section."""
        return cls(noise.declared_torque_ratio, noise.declared_torque_floor_Nm)

    def bound(self, tau: ArrayLike) -> np.ndarray:
        """ratio·|τ| + floor: the bound on |τ_meas − τ| of a sample whose true torque is τ."""
        return self.ratio * np.abs(tau) + self.floor_Nm

    def bound_from_measured(self, tau_meas: ArrayLike, reading_radius: np.ndarray | None = None) -> np.ndarray:
        """The same bound from what was measured: |τ| ≤ (|τ_meas| + floor)/(1 − ratio), so
        |τ_meas − τ| ≤ bound(τ_meas)/(1 − ratio). reading_radius ρ: τ_meas is only known within ρ of
        the reading (a lag interval, estimation/lag.py): bound(|τ_meas| + ρ)/(1 − ratio) + ρ.
        Needs ratio < 1 (the caller checks)."""
        if reading_radius is None:
            return self.bound(tau_meas) / (1.0 - self.ratio)
        return self.bound(np.abs(tau_meas) + reading_radius) / (1.0 - self.ratio) + reading_radius
