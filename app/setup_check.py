"""Checks that make a wrong set-up an error before a run starts (exit 2, one line naming the file
and the field): a prior that does not contain the simulated payload's truth, a start pose outside
the joint limits, a payload of non-positive mass. `safesysid run` and `sweep` call check_setup
after loading the scenario; the robot's own files are checked where they are read
(systems/model/robot_model.py, systems/planner/reachability.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from safesysid.systems.config import Scenario, ScenarioError
from safesysid.systems.model import inertial
from safesysid.systems.model.loading import robot_from_scenario

if TYPE_CHECKING:
    from safesysid.systems.model.robot_model import RobotModel


def check_setup(s: Scenario) -> None:
    """ScenarioError naming the scenario file and field when the set-up cannot be run as declared."""
    from safesysid.systems.plant.arm_plant import scenario_dumbbell

    robot = robot_from_scenario(s)
    _check_start_pose(s, robot)
    _check_start_clear(s, robot)
    dumbbell = scenario_dumbbell(s)
    if dumbbell is not None and not dumbbell.mass_kg > 0:
        raise ScenarioError(
            f"{s.source}: payload.dumbbell: {dumbbell.name!r} has mass {dumbbell.mass_kg} kg (must be > 0)"
        )
    _check_prior_contains_truth(s, robot, dumbbell)


def _check_start_pose(s, robot):
    jp = robot.joint_params
    q0 = np.asarray(s.q0_rad, float)
    outside = [
        f"{name} {q:.4f} not in [{lo:.4f}, {hi:.4f}]"
        for name, q, lo, hi in zip(jp.names, q0, jp.position_lower, jp.position_upper)
        if not lo <= q <= hi
    ]
    if outside:
        raise ScenarioError(f"{s.source}: q0_rad: outside the joint limits of {robot.source}: {'; '.join(outside)}")


def _check_start_clear(s, robot):
    """The arm's link shapes and payload (the referee's geometry, Drake signed distance) clear of
    every obstacle at q0: a run that starts in contact has failed before it moves."""
    from pydrake.systems.framework import DiagramBuilder
    from safesysid.systems.plant.station import add_real_arm

    builder = DiagramBuilder()
    arm = add_real_arm(builder, s, robot=robot)
    diagram = builder.Build()
    ctx = diagram.CreateDefaultContext()
    arm.plant.SetPositions(arm.plant.GetMyMutableContextFromRoot(ctx), arm.instance, np.asarray(s.q0_rad, float))
    query = arm.scene_graph.get_query_output_port().Eval(arm.scene_graph.GetMyContextFromRoot(ctx))
    inspector = query.inspector()
    touching = sorted(
        {
            f"{inspector.GetName(p.id_A)} / {inspector.GetName(p.id_B)}"
            for p in query.ComputeSignedDistancePairwiseClosestPoints(0.0)
            if p.distance < 0
        }
    )
    if touching:
        raise ScenarioError(f"{s.source}: q0_rad: the arm touches an obstacle at the start ({'; '.join(touching)})")


def _check_prior_contains_truth(s, robot, dumbbell):
    """The end effector's true theta (its nominal body plus the scenario's payload) inside
    initial_interval: otherwise the interval the run publishes is not a guarantee of anything."""
    from safesysid.systems.plant.arm_plant import true_theta

    truth = true_theta(robot, dumbbell)[robot.ee_slice]
    lower, upper = (np.asarray(v, float) for v in (s.initial_interval.lower, s.initial_interval.upper))
    bad = [
        f"{name} {t:.4g} not in [{lo:.4g}, {hi:.4g}]"
        for name, t, lo, hi in zip(inertial.NAMES, truth, lower, upper)
        if not lo <= t <= hi
    ]
    if bad:
        payload = dumbbell.name if dumbbell is not None else "none"
        raise ScenarioError(
            f"{s.source}: initial_interval: does not contain the simulated end effector's truth "
            f"(payload.dumbbell {payload!r}): {'; '.join(bad)}"
        )


def payloads_inside_prior(s: Scenario, robot: RobotModel, names: Sequence[str]) -> list[str]:
    """The payloads of `names` (dumbbells, or "none") whose truth the scenario's prior contains:
    the ones a randomized trial may draw (a sweep tests the guarantees, not a wrong set-up)."""
    from safesysid.systems.model.loading import resolve_path, scenario_dir
    from safesysid.systems.model.payload import load_dumbbells
    from safesysid.systems.plant.arm_plant import true_theta

    bells = load_dumbbells(resolve_path(s.payload.dumbbells_file, scenario_dir(s)))
    lower, upper = (np.asarray(v, float) for v in (s.initial_interval.lower, s.initial_interval.upper))

    def inside(name):
        truth = true_theta(robot, None if name == "none" else bells[name])[robot.ee_slice]
        return bool(np.all(lower <= truth) and np.all(truth <= upper))

    return [name for name in names if inside(name)] or list(names)
