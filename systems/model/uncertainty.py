"""The declared box of the robot's own parameters: nominal +- max(ratio |nominal|, floor).

One definition for the controller, the planner, the estimator and the drawn real arm; the floors
are a scenario field (systems/config.py ParameterFloors).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.config import InitialInterval, Noise, ParameterFloors
from safesysid.systems.math.intervals import Interval
from safesysid.systems.model.robot_model import RobotModel


def parameter_radius(
    robot: RobotModel, inertial_ratio: float, friction_ratio: float, *, floors: ParameterFloors | None = None
) -> np.ndarray:
    """(14 n,) half-widths max(ratio |theta|, floor) around the model's nominal theta (the end
    effector's entries too; callers replace them by its own box)."""
    floors = ParameterFloors() if floors is None else floors
    n = robot.n
    ratio = np.where(np.arange(14 * n) < 10 * n, inertial_ratio, friction_ratio)
    return np.maximum(ratio * np.abs(robot.theta), floors.per_parameter(n))


# ---- parameter boxes ------------------------------------------------------------------------------
def parameter_box(
    robot: RobotModel,
    theta_e_nominal: ArrayLike,
    theta_e_lower: ArrayLike,
    theta_e_upper: ArrayLike,
    *,
    rest_ratio: float | None = None,
    friction_ratio: float | None = None,
    floors: ParameterFloors | None = None,
) -> tuple[np.ndarray, Interval]:
    """(theta0, [theta]) over all 14 n parameters: the end effector from the given box, the rest
    of the robot +- max(ratio |theta|, floor) around the model (ratios from the parameter YAML and
    the default floors unless given)."""
    doc = (robot.extra.get("params_doc") or {}).get("uncertainty", {})
    rest_ratio = doc.get("link_inertial_ratio", 0.0) if rest_ratio is None else rest_ratio
    friction_ratio = doc.get("friction_ratio", 0.0) if friction_ratio is None else friction_ratio
    theta0 = robot.theta.copy()
    rad = parameter_radius(robot, rest_ratio, friction_ratio, floors=floors)
    theta0[robot.ee_slice] = theta_e_nominal
    lo, hi = theta0 - rad, theta0 + rad
    lo[robot.ee_slice], hi[robot.ee_slice] = theta_e_lower, theta_e_upper
    return theta0, Interval(lo, hi)


def prior_box(
    robot: RobotModel, initial_interval: InitialInterval, noise: Noise, *, exact: bool = False
) -> tuple[np.ndarray, Interval]:
    """(theta0, [theta]) a run starts from: the end effector's scenario.initial_interval, the rest
    of the robot nominal +- max(noise.theta_r_ratio |theta|, noise.theta_r_floor). exact: the
    model's own theta with zero width (the "wrong"-model baseline)."""
    if exact:
        theta0 = robot.theta.copy()
        return theta0, Interval(theta0, theta0)
    ii, ratio = initial_interval, noise.theta_r_ratio
    return parameter_box(
        robot,
        np.array(ii.nominal),
        np.array(ii.lower),
        np.array(ii.upper),
        rest_ratio=ratio,
        friction_ratio=ratio,
        floors=noise.theta_r_floor,
    )
