"""The declared box of the robot's own parameters: nominal +- max(ratio |nominal|, floor).

One definition for the controller, the planner, the estimator and the drawn real arm; the floors
are a scenario field (systems/config.py ParameterFloors).
"""

from __future__ import annotations

import numpy as np

from .config import ParameterFloors
from .robot_model import RobotModel

__all__ = ["ParameterFloors", "parameter_radius"]


def parameter_radius(
    robot: RobotModel, inertial_ratio: float, friction_ratio: float, floors: ParameterFloors | None = None
) -> np.ndarray:
    """(14 n,) half-widths max(ratio |theta|, floor) around the model's nominal theta (the end
    effector's entries too; callers replace them by its own box)."""
    floors = ParameterFloors() if floors is None else floors
    n = robot.n
    ratio = np.where(np.arange(14 * n) < 10 * n, inertial_ratio, friction_ratio)
    return np.maximum(ratio * np.abs(robot.theta), floors.per_parameter(n))
