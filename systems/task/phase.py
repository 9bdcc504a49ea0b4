"""The task phase of a run (paper §VII), as pure functions: the scenario's cached task trajectory,
the verified move back to its start after identification, the placement target and error, and
the judgement of a run (which failure came first, in which phase).

Why a return move rather than re-planning the task from where identification ended: the task
trajectory then depends only on the scenario (the paper's "pre-defined trajectory" every method
must follow), so it is solved once and cached; the return move is a one-piece minimum-jerk move
from rest to rest under the same constraints (limits shrunk by the tube, torque with the payload
model, the planner's spheres against the obstacles with the window and tube margins; the spheres
of the payload actually held, as in the identification plans that ended there), solved in a
second or less from its straight-line guess.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from safesysid.systems.config import Obstacle, Scenario
from safesysid.systems.model.loading import resolve_path, scenario_dir
from safesysid.systems.task import cache as task_cache
from safesysid.systems.task import trajectory as tt
from safesysid.systems.task.problem import TaskProblem

if TYPE_CHECKING:
    from safesysid.systems.model.payload import Dumbbell

PHASES = ("identification", "task")
AT_START_TOL_RAD = 1e-9  # closer than this to the task start: no return move


def cache_dir(scenario: Scenario) -> Path:
    """task.cache_dir (relative to the scenario), or $XDG_CACHE_HOME|~/.cache /safesysid/task."""
    if scenario.task.cache_dir:
        return resolve_path(scenario.task.cache_dir, scenario_dir(scenario))
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "safesysid" / "task"


def task_plan(scenario: Scenario, problem: TaskProblem | None = None) -> tuple[TaskProblem, tt.TaskResult]:
    """(TaskProblem, TaskResult) of the scenario's task, through the cache."""
    problem = problem or tt.task_problem_from_scenario(scenario)
    return problem, task_cache.task_trajectory_cached(problem, cache_dir(scenario))


def return_move(
    problem: TaskProblem, q_from: np.ndarray, duration_s: float, *, held: Dumbbell | None = None
) -> tt.TaskResult | None:
    """Rest-to-rest move from q_from to the task start (one degree-5 piece of duration_s) under
    the task's constraints; None when q_from already is the start. held: the payload in the
    gripper, whose geometry the collision constraints use (as the identification plans that
    ended at q_from did; the task's payload model, e.g. the 8 lb one, may be larger and start
    inside an obstacle's margin there); the torque keeps the task's parameters (model)."""
    q_from = np.asarray(q_from, float)
    if np.max(np.abs(q_from - problem.q_start)) < AT_START_TOL_RAD:
        return None
    settings = dataclasses.replace(problem.settings, num_pieces=1, duration_s=float(duration_s))
    move = dataclasses.replace(
        problem,
        q_start=q_from,
        goal_q=problem.q_start,
        place_xyz=None,
        settings=settings,
        dumbbell=problem.dumbbell if held is None else held,
    )
    return tt.solve_task_trajectory(move)


def stack_boxes(platform: Obstacle, dumbbells: Sequence[Dumbbell]) -> list[Obstacle]:
    """The dumbbells already placed on `platform` (bottom first) as obstacle boxes stacked on its
    top centre: each lies on its heads (height 2 x head radius) at an unknown yaw, so its box has a
    square footprint of side sqrt(length^2 + (2 head radius)^2), which holds it at any yaw. They
    stand for the placed dumbbells in the planner's, the task trajectory's and the referee's
    world (welded: a model of a stack that stays put, not simulated free bodies)."""
    x, y, z = np.asarray(platform.xyz_m, float)
    top = z + 0.5 * float(platform.size_m[2])
    boxes = []
    for k, bell in enumerate(dumbbells):
        height, side = 2 * bell.head_radius_m, float(np.hypot(bell.length_m, 2 * bell.head_radius_m))
        boxes.append(
            Obstacle(
                name=f"stacked_{k + 1}_{bell.name}",
                xyz_m=[float(x), float(y), float(top + 0.5 * height)],
                rpy_rad=[0.0, 0.0, 0.0],
                size_m=[side, side, height],
            )
        )
        top += height
    return boxes


def placement_target(scenario: Scenario, dumbbell: Dumbbell | None) -> tuple[np.ndarray | None, str]:
    """(target xyz, "settled" | "release") of the payload centre, or (None, "") without a
    placement. With a platform: resting on its top, under its centre (top + the payload's resting
    radius); with place_xyz_m only: the centre at release."""
    task = scenario.task
    if task.goal_q_rad or dumbbell is None:
        return None, ""
    if task.platform:
        platform = next(ob for ob in scenario.obstacles if ob.name == task.platform)
        return tt.placement_above(platform, dumbbell, 0.0), "settled"
    if task.place_xyz_m:
        return np.asarray(task.place_xyz_m, float), "release"
    return None, ""


def phase_at(t: float, t_switch: float) -> str:
    return PHASES[int(t >= t_switch - 1e-12)]


def first_failure(
    checks: Iterable[tuple[str, Sequence[float] | np.ndarray]], t_switch: float
) -> tuple[str | None, str | None, float | None]:
    """checks: [(failure name, times at which it is violated)] in priority order (contracts.md).
    Returns (failure, phase, t) of the first check with a violation, or (None, None, None)."""
    for name, times in checks:
        times = np.atleast_1d(np.asarray(times, float))
        if times.size:
            t = float(times.min())
            return name, phase_at(t, t_switch), t
    return None, None, None
