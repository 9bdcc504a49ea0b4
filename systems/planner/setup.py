"""What one planning problem (problem.py, torque_box.py) reads of the planner that poses it:
safe_planner.SafePlanner is one. A Protocol, so the problem's modules never import the planner's."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from safesysid.systems.config import Planner
    from safesysid.systems.controller.armour import TrackingBounds
    from safesysid.systems.model.robot_model import RobotModel
    from safesysid.systems.planner.reachability import Boxes, Spheres


class PlannerSetup(Protocol):
    robot: RobotModel
    config: Planner
    k_center: np.ndarray  # (n,) plans end at q0 + k_center + k_range * k
    k_range: np.ndarray
    tracking: TrackingBounds
    spheres: Spheres  # the arm's and the payload's collision spheres
    lipschitz: np.ndarray  # their centres' Lipschitz constants per joint
    boxes: Boxes  # the obstacles
    floor_z: float | None
    floor_exempt: np.ndarray  # spheres whose height no joint changes
    torque_shrink_steps: int
    torque_group: int
    spread_rows: int

    @property
    def weighs_rows(self) -> bool: ...

    def row_weights(self, q: np.ndarray, v: np.ndarray, a: np.ndarray, theta0: np.ndarray) -> np.ndarray: ...
