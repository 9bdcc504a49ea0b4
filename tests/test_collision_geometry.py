"""The planner's collision spheres enclose the robot's real geometry, and the referee measures
that geometry, not the spheres.

The real geometry is what Drake's SceneGraph holds for the simulated arm (add_real_arm): every
shape of every robot body, collision (proximity) and visual (illustration) roles alike, plus the
dumbbell's cylinders. Each shape is sampled densely (surface and nested shells inside), posed by
SceneGraph at many joint configurations, and every sample must lie inside a planner sphere
carried by the same body (spheres ride on body frames, so the check is per carrier body).
"""

import numpy as np
import pytest
from helpers import params_with_spheres
from pydrake.geometry import Box, Capsule, Cylinder, Role, Sphere
from pydrake.systems.framework import DiagramBuilder
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.systems.model.payload import load_dumbbells
from safesysid.systems.model.robot_model import MODELS_DIR, carrier_index, load_robot
from safesysid.systems.planner import reachability as reach
from safesysid.systems.plant.station import add_real_arm

TOLERANCE_M = 1e-9


def _ring(n):
    return np.linspace(0.0, 2 * np.pi, 2 * n, endpoint=False)


def _disk_side(radius, length, n):
    """Side of a z-aligned cylinder (radius, length) centred at the origin."""
    u, z = np.meshgrid(_ring(n), np.linspace(-length / 2, length / 2, n))
    return np.stack([radius * np.cos(u), radius * np.sin(u), z], -1).reshape(-1, 3)


def sample_shape(shape, n=24):
    """Points of a Drake shape in its geometry frame: the surface and shells scaled toward the
    centre (every shape here is convex and centred at its frame origin)."""
    if isinstance(shape, Capsule):
        a, length = shape.radius(), shape.length()
        u, th = np.meshgrid(_ring(n), np.linspace(0.0, np.pi / 2, n))
        cap = np.stack([a * np.cos(u) * np.cos(th), a * np.sin(u) * np.cos(th), a * np.sin(th)], -1).reshape(-1, 3)
        surface = np.vstack([_disk_side(a, length, n), cap + [0, 0, length / 2], cap * [1, 1, -1] - [0, 0, length / 2]])
    elif isinstance(shape, Cylinder):
        a, length = shape.radius(), shape.length()
        u, r = np.meshgrid(_ring(n), np.linspace(0.0, a, n))
        disk = np.stack([r * np.cos(u), r * np.sin(u), 0 * r], -1).reshape(-1, 3)
        surface = np.vstack([_disk_side(a, length, n), disk + [0, 0, length / 2], disk - [0, 0, length / 2]])
    elif isinstance(shape, Box):
        half = np.asarray(shape.size()) / 2
        a, b = (x.ravel() for x in np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n)))
        faces = []
        for axis in range(3):
            others = [i for i in range(3) if i != axis]
            for side in (-1.0, 1.0):
                face = np.zeros((len(a), 3))
                face[:, axis], face[:, others[0]], face[:, others[1]] = side, a, b
                faces.append(face * half)
        surface = np.vstack(faces)
    elif isinstance(shape, Sphere):
        u, th = np.meshgrid(_ring(n), np.linspace(-np.pi / 2, np.pi / 2, n))
        surface = shape.radius() * np.stack([np.cos(u) * np.cos(th), np.sin(u) * np.cos(th), np.sin(th)], -1).reshape(
            -1, 3
        )
    else:
        raise AssertionError(f"no sampler for {type(shape).__name__}")
    return np.vstack([f * surface for f in (1.0, 0.75, 0.5, 0.25, 0.0)])


def real_arm_scene(robot, dumbbell, scenario_file="quickstart.yaml"):
    """The simulated arm (with `dumbbell` grasped) as SceneGraph sees it."""
    scenario = load_scenario(SCENARIOS_DIR / scenario_file)
    builder = DiagramBuilder()
    arm = add_real_arm(builder, scenario, robot=robot, dumbbell=dumbbell)
    diagram = builder.Build()
    return arm, diagram, diagram.CreateDefaultContext()


def worst_protrusions(robot, dumbbell, configurations, scenario_file="quickstart.yaml"):
    """{'link shape': max over samples and configurations of (distance outside the nearest
    sphere carried by the same body)}; +inf when that body carries no sphere."""
    arm, diagram, ctx = real_arm_scene(robot, dumbbell, scenario_file)
    plant, sg = arm.plant, arm.scene_graph
    spheres = reach.arm_spheres(robot).concat(reach.payload_spheres(robot, dumbbell))
    inspector = sg.model_inspector()
    world = inspector.world_frame_id()
    shapes = []
    for role in (Role.kProximity, Role.kIllustration):
        for gid in inspector.GetAllGeometryIds(role):
            frame = inspector.GetFrameId(gid)
            if frame == world:
                continue  # obstacles and the floor
            body = plant.GetBodyFromFrameId(frame)
            carrier = carrier_index(plant, body, robot.body_names)
            kind = "collision" if role == Role.kProximity else "visual"
            label = f"{body.name()} {type(inspector.GetShape(gid)).__name__} ({kind})"
            shapes.append((gid, label, sample_shape(inspector.GetShape(gid)), spheres.body == carrier))
    worst = {}
    pctx = plant.GetMyMutableContextFromRoot(ctx)
    for q in configurations:
        plant.SetPositions(pctx, arm.instance, q)
        query = sg.get_query_output_port().Eval(sg.GetMyContextFromRoot(ctx))
        centres, _ = reach.sphere_centres(robot.tree, spheres, q[None], with_jacobian=False)
        for gid, label, points, own in shapes:
            if not own.any():
                worst[label] = np.inf
                continue
            world_points = query.GetPoseInWorld(gid).multiply(points.T).T
            gap = np.linalg.norm(world_points[:, None] - centres[0, own][None], axis=-1) - spheres.radius[own]
            worst[label] = max(worst.get(label, -np.inf), float(gap.min(1).max()))
    return worst


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def configurations(robot, count, seed=0):
    rng = np.random.default_rng(seed)
    jp = robot.joint_params
    lo = np.where(np.isfinite(jp.position_lower), jp.position_lower, -np.pi)
    hi = np.where(np.isfinite(jp.position_upper), jp.position_upper, np.pi)
    return [np.zeros(robot.n)] + [rng.uniform(lo, hi) for _ in range(count)]


@pytest.mark.parametrize("bell", ["none", "4lb", "8lb"])
def test_planner_spheres_enclose_every_link_and_the_payload(robot, bell):
    dumbbell = None if bell == "none" else load_dumbbells(MODELS_DIR / "dumbbells.yaml")[bell]
    worst = worst_protrusions(robot, dumbbell, configurations(robot, 12))
    for label, gap in worst.items():
        print(f"{bell:5s} {label:55s} worst protrusion {gap * 100:8.3f} cm")
    outside = {label: gap for label, gap in worst.items() if gap > TOLERANCE_M}
    assert not outside, f"geometry outside the planner's spheres [m]: {outside}"
    if dumbbell is not None:
        assert any(label.startswith("payload Cylinder (collision)") for label in worst)


def test_the_enclosure_check_catches_a_sphere_file_that_misses_the_arm(robot, tmp_path):
    """The same check on a sphere file with the forearm's spheres 2 cm smaller: the forearm
    capsule sticks out (the check is live), and the referee's geometry is untouched (it is the
    URDF's, whatever the planner's file says)."""
    import yaml

    doc = yaml.safe_load((MODELS_DIR / "kinova_gen3_spheres.yaml").read_text())
    for sphere in doc["links"]["forearm_link"]:
        sphere["radius_m"] -= 0.02
    spheres = tmp_path / "spheres.yaml"
    spheres.write_text(yaml.safe_dump(doc))
    shrunk = load_robot(params_path=params_with_spheres(tmp_path, spheres))
    worst = worst_protrusions(shrunk, None, configurations(shrunk, 2))
    assert worst["forearm_link Capsule (collision)"] > 0.01
    assert max(gap for label, gap in worst.items() if not label.startswith("forearm")) <= TOLERANCE_M
    assert worst.keys() == worst_protrusions(robot, None, configurations(robot, 0)).keys()


def test_the_planner_checks_obstacles_against_the_fixed_base(robot):
    """The base cannot move, yet it has (world-fixed) planner spheres: a box 1 cm from the base
    capsule, inside those spheres and clear of every moving one, makes the planner refuse to
    start, naming the base; 5 cm away (outside them) it plans."""
    from safesysid.systems.config import Obstacle, Planner
    from safesysid.systems.planner.safe_planner import SafePlanner

    q0 = np.array([0.0, 0.26, 0.0, 2.0, 0.0, 0.9, 1.57])
    theta = robot.theta
    reasons = {}
    for gap in (0.01, 0.05):
        box = Obstacle(name="by_the_base", xyz_m=[-(0.045 + gap + 0.05), 0.0, 0.05], size_m=[0.1, 0.1, 0.1])
        planner = SafePlanner(robot, Planner(num_cost_samples=16), obstacles=[box], payload=None, tracking=None)
        problem = planner.problem(q0, np.zeros(robot.n), np.zeros(robot.n), theta, theta, theta)
        reasons[gap] = problem.reason
    assert "base_link_sphere" in reasons[0.01] and "by_the_base" in reasons[0.01]
    assert reasons[0.05] == ""
