"""The declared box of the robot's own parameters: nominal +- max(ratio |nominal|, floor).

One definition for the controller, the planner, the estimator and the drawn real arm. (No
`from __future__ import annotations` here: Drake's yaml loader reads these field types.)
"""
from dataclasses import dataclass

import numpy as np


@dataclass
class ParameterFloors:
    """Absolute floor of the half-width of each robot parameter in [theta], per kind (SI units in
    the names): the box is nominal +- max(ratio |nominal|, floor), so parameters whose nominal is
    zero (torque offsets beta, products of inertia, some first moments) are uncertain too."""

    mass_kg: float = 0.01
    first_moment_kgm: float = 0.0005
    inertia_kgm2: float = 5e-5
    coulomb_Nm: float = 0.01
    viscous_Nms_rad: float = 0.01
    armature_kgm2: float = 0.01
    offset_Nm: float = 0.05

    def per_parameter(self, n):
        """(14 n,) floors in theta order: per body [m, m c (3), I (6)], per joint [Fc, Fv, Ia, beta]."""
        body = [self.mass_kg] + [self.first_moment_kgm] * 3 + [self.inertia_kgm2] * 6
        joint = [self.coulomb_Nm, self.viscous_Nms_rad, self.armature_kgm2, self.offset_Nm]
        return np.concatenate([np.tile(body, n), np.tile(joint, n)]).astype(float)


def parameter_radius(robot, inertial_ratio, friction_ratio, floors: ParameterFloors | None = None):
    """(14 n,) half-widths max(ratio |theta|, floor) around the model's nominal theta (the end
    effector's entries too; callers replace them by its own box)."""
    floors = ParameterFloors() if floors is None else floors
    n = robot.n
    ratio = np.where(np.arange(14 * n) < 10 * n, inertial_ratio, friction_ratio)
    return np.maximum(ratio * np.abs(robot.theta), floors.per_parameter(n))
