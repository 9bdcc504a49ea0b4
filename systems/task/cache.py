"""Cache of task trajectories (systems/task/trajectory.py): one JSON file per problem, keyed by a
sha256 of everything the result depends on."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING

from safesysid.systems.task import trajectory as tt
from safesysid.systems.task.problem import TaskProblem, jsonable
from safesysid.systems.task.trajectory import VERSION, TaskResult, task_problem_from_scenario

if TYPE_CHECKING:
    from safesysid.systems.config import Scenario


def cache_key(problem: TaskProblem, solver: str | None = None, fallback: bool = True) -> str:
    """sha256 of every input: model files' contents (URDF, parameter file, sphere file), the
    model arrays, payload, obstacles, floor, start, goal, tube, settings, solver, VERSION."""
    robot = problem.robot
    doc = robot.extra.get("params_doc") or {}
    files = [Path(robot.source)] + (
        [Path(robot.source).parent / doc["planner_spheres"]] if doc.get("planner_spheres") else []
    )
    jp = robot.joint_params
    inputs = {
        "version": VERSION,
        "files": {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in files},
        "params_doc": doc,
        "joint_params": {
            k: getattr(jp, k)
            for k in (
                "names",
                "position_lower",
                "position_upper",
                "velocity_limit",
                "torque_limit",
                "coulomb",
                "viscous",
                "armature",
                "offset",
            )
        },
        "robot_theta": robot.theta,
        "coulomb_smoothing": robot.coulomb_smoothing,
        "end_effector": robot.end_effector,
        "grasp_point": robot.extra.get("grasp_point"),
        "theta": problem.theta,
        "dumbbell": None if problem.dumbbell is None else problem.dumbbell.__dict__,
        "obstacles": [[o.name, list(o.xyz_m), list(o.rpy_rad), list(o.size_m)] for o in problem.obstacles],
        "floor_z": problem.floor_z,
        "q_start": problem.q_start,
        "goal_q": problem.goal_q,
        "place_xyz": problem.place_xyz,
        "tracking": problem.tracking.__dict__,
        "settings": problem.settings.__dict__,
        "solver": solver or problem.settings.solver,
        "fallback": fallback,
    }
    text = json.dumps(jsonable(inputs), sort_keys=True, default=float)
    return hashlib.sha256(text.encode()).hexdigest()


def task_trajectory_cached(
    problem: TaskProblem | Scenario, cache_dir: str | Path, *, solver: str | None = None, fallback: bool = True
) -> TaskResult:
    """solve_task_trajectory through a cache: `cache_dir`/task_<key>.json holds the result for
    the inputs hashed by cache_key; a hit loads it without solving (details['cache'] = 'hit'),
    a miss solves and stores (solver errors are not stored). `problem`: a TaskProblem or a
    scenario with a task section."""
    if not isinstance(problem, TaskProblem):
        problem = task_problem_from_scenario(problem)
    key = cache_key(problem, solver, fallback)
    path = Path(cache_dir) / f"task_{key[:24]}.json"
    if path.is_file():
        try:
            doc = json.loads(path.read_text())
            if doc.get("key") == key:
                res = TaskResult.from_dict(doc["result"])
                res.details.update(cache="hit", cache_file=str(path))
                return res
        except (OSError, ValueError, KeyError, TypeError):
            pass  # unreadable or foreign file: recompute and overwrite
    res = tt.solve_task_trajectory(problem, solver, fallback)  # through the module: patchable
    if res.status != "solver_failed":
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"key": key, "version": VERSION, "result": res.to_dict()}, indent=1))
        tmp.replace(path)  # atomic: a concurrent reader never sees half a file
    res.details.update(cache="miss", cache_file=str(path))
    return res
