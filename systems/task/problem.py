"""The task trajectory's problem: everything it depends on (and the cache key hashes), read by its
constraints (constraints.py) and its solver (trajectory.py)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from safesysid.systems.controller.armour import TrackingBounds
from safesysid.systems.planner import reachability as reach

if TYPE_CHECKING:
    from safesysid.systems.config import Task
    from safesysid.systems.model.payload import Dumbbell
    from safesysid.systems.model.robot_model import RobotModel


@dataclass
class TaskSettings:
    """Numbers of the optimization (scenario `task` section, app/scenario.py)."""

    duration_s: float = 2.0
    num_pieces: int = 2
    collision_samples: int = 200
    torque_samples: int = 41
    torque_margin_ratio: float = 0.2
    solver: str = "snopt"
    max_iterations: int = 500
    max_solve_time_s: float = 120.0  # per solver (all its rounds)

    @classmethod
    def from_task(cls, task: Task) -> TaskSettings:
        return cls(**{f: getattr(task, f) for f in cls.__dataclass_fields__})


@dataclass
class TaskProblem:
    """Everything the task trajectory depends on (and the cache key hashes)."""

    robot: RobotModel  # limits, friction, kinematics
    theta: np.ndarray  # 14 n parameters the torque is computed with (robot + payload model)
    dumbbell: Dumbbell | None  # payload model
    obstacles: list  # scenario Obstacle records (platform included)
    floor_z: float | None
    q_start: np.ndarray
    goal_q: np.ndarray | None = None
    place_xyz: np.ndarray | None = None  # payload centre target (grasp point), base frame
    tracking: TrackingBounds | None = None
    settings: TaskSettings = field(default_factory=TaskSettings)

    def __post_init__(self):
        n = self.robot.n
        self.q_start = np.asarray(self.q_start, float)
        self.goal_q = None if self.goal_q is None or len(self.goal_q) == 0 else np.asarray(self.goal_q, float)
        self.place_xyz = (
            None if self.place_xyz is None or len(self.place_xyz) == 0 else np.asarray(self.place_xyz, float)
        )
        if (self.goal_q is None) == (self.place_xyz is None):
            raise ValueError("a task needs exactly one of goal_q and place_xyz")
        self.tracking = TrackingBounds.coerce(self.tracking, n)
        self.boxes = reach.Boxes.from_obstacles(list(self.obstacles))
        self.spheres = reach.arm_spheres(self.robot).concat(reach.payload_spheres(self.robot, self.dumbbell))


def jsonable(x: object) -> object:
    """x with numpy arrays and scalars as lists and Python numbers (for JSON and hashing)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x
