"""Randomized scenes for Monte-Carlo safety runs (issue 5): random start near a base pose,
1-4 random boxes near the arm (never touching it at the start), random payload 0-8 lb.
With near_clearance_m=(lo, hi) the first box is placed at a clearance drawn in [lo, hi] from the
planner's spheres (arm and payload) at the start: adversarially close, yet outside them, so the
planner can start (the real link shapes are inside the spheres: their clearance is at least that)."""

from __future__ import annotations

import copy

import numpy as np
from safesysid.setup_check import payloads_inside_prior
from safesysid.systems.config import Obstacle, Scenario
from safesysid.systems.model.loading import robot_from_scenario

PAYLOADS = ("none", "4lb", "5lb", "6lb", "7lb", "8lb")


def _sphere_centres(robot, q, dumbbell=None):
    """Planner sphere centres and radii at q: the arm's, and the payload's when given."""
    from safesysid.systems.planner.reachability import arm_spheres, payload_spheres, sphere_centres

    spheres = arm_spheres(robot)
    if dumbbell is not None:
        spheres = spheres.concat(payload_spheres(robot, dumbbell))
    centres, _ = sphere_centres(robot.tree, spheres, np.asarray(q, float)[None], with_jacobian=False)
    return centres[0], spheres.radius


def _clearance(points, radii, box: Obstacle):
    from pydrake.math import RollPitchYaw

    rot = RollPitchYaw(box.rpy_rad).ToRotationMatrix().matrix()
    local = (points - np.asarray(box.xyz_m)) @ rot
    half = np.asarray(box.size_m) / 2
    outside = np.linalg.norm(np.maximum(np.abs(local) - half, 0.0), axis=1)
    inside = np.minimum(np.max(np.abs(local) - half, axis=1), 0.0)
    return float(np.min(outside + inside - radii))


def _box_on_floor(name, centre, size, yaw):
    centre = np.array(centre, float)
    centre[2] = max(centre[2], size[2] / 2)  # rest on or above the floor
    return Obstacle(name=name, xyz_m=centre.tolist(), rpy_rad=[0.0, 0.0, float(yaw)], size_m=list(map(float, size)))


def _random_direction(rng):
    """A random unit direction, flattened toward the horizontal."""
    direction = rng.normal(size=3)
    direction[2] *= 0.3
    return direction / np.linalg.norm(direction)


def near_box(
    points: np.ndarray, radii: np.ndarray, rng: np.random.Generator, *, clearance_m: float, attempts: int = 50
) -> Obstacle | None:
    """A random box whose clearance from the spheres (points, radii) is clearance_m (to 0.1 mm):
    pushed out from a random sphere along a random direction, the distance found by bisection."""
    for _ in range(attempts):
        anchor = points[rng.integers(len(points))]
        direction = _random_direction(rng)
        size = rng.uniform(0.05, 0.3, 3)
        yaw = rng.uniform(-np.pi, np.pi)

        def gap(dist):
            # called only within this iteration, so the loop variables are the current ones
            box = _box_on_floor("near", anchor + dist * direction, size, yaw)  # noqa: B023
            return _clearance(points, radii, box) - clearance_m

        lo, hi = 0.0, 2.0
        if gap(lo) >= 0 or gap(hi) <= 0:
            continue
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if gap(mid) < 0 else (lo, mid)
        if abs(gap(hi)) < 1e-4:
            return _box_on_floor("near", anchor + hi * direction, size, yaw)
    return None


def random_scene(
    base: Scenario,
    rng: np.random.Generator,
    start_spread_rad: float = 0.15,
    *,
    min_start_clearance_m: float = 0.08,
    seed: int | None = None,
    near_clearance_m: tuple[float, float] | None = None,
) -> Scenario:
    """A copy of `base` with a random start, random boxes near the arm and a random payload
    (near_clearance_m: (lo, hi) of the first box's clearance from the planner's spheres)."""
    scene = copy.deepcopy(base)
    robot = robot_from_scenario(base)
    jp = robot.joint_params
    q0 = np.asarray(base.q0_rad, float) + rng.uniform(-start_spread_rad, start_spread_rad, robot.n)
    q0 = np.clip(q0, jp.position_lower + 0.3, jp.position_upper - 0.3)
    scene.q0_rad = q0.tolist()
    scene.payload.dumbbell = str(rng.choice(payloads_inside_prior(base, robot, PAYLOADS)))
    points, radii = _sphere_centres(robot, q0)
    # Dumbbell clearance is covered by the gripper spheres' margin plus min_start_clearance_m.
    boxes = []
    if near_clearance_m is not None:
        from safesysid.systems.plant.arm_plant import scenario_dumbbell

        held_points, held_radii = _sphere_centres(robot, q0, scenario_dumbbell(scene))  # with the payload's
        near = near_box(held_points, held_radii, rng, clearance_m=rng.uniform(*near_clearance_m))
        boxes += [] if near is None else [near]
    for _ in range(200):
        if len(boxes) >= rng.integers(1, 5):
            break
        anchor = points[rng.integers(len(points))]
        direction = _random_direction(rng)
        size = rng.uniform(0.05, 0.3, 3)
        centre = anchor + direction * (np.max(size) / 2 + rng.uniform(0.12, 0.35))
        if centre[2] - size[2] / 2 < 0.0:  # rest on or above the floor
            centre[2] = size[2] / 2 + rng.uniform(0.0, 0.05)
        box = Obstacle(
            name=f"box{len(boxes)}",
            xyz_m=centre.tolist(),
            rpy_rad=[0.0, 0.0, float(rng.uniform(-np.pi, np.pi))],
            size_m=size.tolist(),
        )
        if _clearance(points, radii, box) >= min_start_clearance_m + 0.15:  # 0.15: dumbbell reach beyond the spheres
            boxes.append(box)
    scene.obstacles = boxes
    # A random scene measures the guarantees: the simulated arm's own parameters are drawn in their
    # declared box (A1), not the model's nominal ones (summary.json robot_parameters says which).
    scene.plant.robot_parameters = "drawn"
    scene.seed = int(rng.integers(1 << 30)) if seed is None else seed
    scene.name = f"{base.name}_random"
    return scene
