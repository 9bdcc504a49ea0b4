"""A second arm from its published figures: the Franka Emika Panda (models/make_panda_urdf.py).

The planner's spheres of any arm come from its collision shapes (models/cover_spheres.py): each
primitive is sampled (surface and inner shells) and found inside its spheres, on random shapes
and on the Panda as Drake poses it. The hand welded to the last link is part of the end-effector
body; a prior derived from a payload range contains every payload of that range.
"""

import numpy as np
import pytest
from pydrake.geometry import Box, Capsule, Cylinder, Sphere
from pydrake.math import RigidTransform, RollPitchYaw
from safesysid.models import cover_spheres, make_panda_urdf, make_ur5e_urdf
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.systems.config import ScenarioError
from safesysid.systems.estimation.prior import payload_range_prior
from safesysid.systems.model import inertial
from safesysid.systems.model.payload import load_dumbbells
from safesysid.systems.model.robot_model import MODELS_DIR, ModelError, load_robot
from test_collision_geometry import TOLERANCE_M, configurations, sample_shape, worst_protrusions

PANDA_PARAMS = MODELS_DIR / "panda_params.yaml"


@pytest.fixture(scope="module")
def panda():
    return load_robot(params_path=PANDA_PARAMS)


def _random_shapes(rng, count):
    kinds = [
        lambda: Sphere(rng.uniform(0.01, 0.08)),
        lambda: Capsule(rng.uniform(0.01, 0.08), rng.uniform(0.0, 0.4)),
        lambda: Cylinder(rng.uniform(0.01, 0.08), rng.uniform(0.001, 0.4)),
        lambda: Box(*rng.uniform(0.005, 0.3, 3)),
    ]
    for k in range(count):
        pose = RigidTransform(RollPitchYaw(rng.uniform(-np.pi, np.pi, 3)), rng.uniform(-0.2, 0.2, 3))
        yield kinds[k % 4](), pose


def test_the_generic_spheres_cover_every_primitive_shape():
    """Random spheres, capsules, cylinders and boxes at random poses, margins 2 mm to 3 cm:
    every sample of every shape lies inside one of its spheres (the rule of cover_spheres)."""
    rng = np.random.default_rng(0)
    for shape, pose in _random_shapes(rng, 80):
        margin = rng.uniform(0.002, 0.03)
        spheres = cover_spheres.shape_spheres(shape, pose, margin)
        centres = np.array([c for c, _ in spheres])
        radii = np.array([r for _, r in spheres])
        points = pose.multiply(sample_shape(shape).T).T
        gap = (np.linalg.norm(points[:, None] - centres[None], axis=-1) - radii).min(1).max()
        assert gap <= TOLERANCE_M, f"{type(shape).__name__} margin {margin:.4f}: a point {gap:.4f} m outside"


def test_the_panda_files_are_the_generators_output():
    """models/panda.urdf and panda_spheres.yaml are what make_panda_urdf.py writes (no hand edits)."""
    assert (MODELS_DIR / "panda.urdf").read_text() == make_panda_urdf.urdf()
    spheres = cover_spheres.model_spheres(MODELS_DIR / "panda.urdf", make_panda_urdf.SPHERE_MARGIN_M)
    assert (MODELS_DIR / "panda_spheres.yaml").read_text() == cover_spheres.spheres_yaml(spheres, "make_panda_urdf.py")


def test_the_ur5e_files_are_the_generators_output_and_its_spheres_enclose_it():
    """The third arm (6 joints), brought in by docs/own-robot.md's steps: its files are its
    generator's output, and its spheres hold every link shape, the tool and the payload."""
    assert (MODELS_DIR / "ur5e.urdf").read_text() == make_ur5e_urdf.urdf()
    assert (MODELS_DIR / "ur5e_params.yaml").read_text() == make_ur5e_urdf.params_yaml()
    spheres = cover_spheres.model_spheres(MODELS_DIR / "ur5e.urdf", make_ur5e_urdf.SPHERE_MARGIN_M)
    assert (MODELS_DIR / "ur5e_spheres.yaml").read_text() == cover_spheres.spheres_yaml(spheres, "make_ur5e_urdf.py")
    ur5e = load_robot(params_path=MODELS_DIR / "ur5e_params.yaml")
    assert ur5e.n == 6 and ur5e.body_names[ur5e.end_effector] == "wrist_3_link"
    dumbbell = load_dumbbells(MODELS_DIR / "dumbbells.yaml")["4lb"]
    worst = worst_protrusions(ur5e, dumbbell, configurations(ur5e, 4), "ur5e_quickstart.yaml")
    assert max(worst.values()) <= TOLERANCE_M, worst
    assert any(label.startswith("tool") for label in worst)


@pytest.mark.parametrize("bell", ["none", "4lb"])
def test_the_panda_spheres_enclose_every_link_shape_and_the_payload(panda, bell):
    dumbbell = None if bell == "none" else load_dumbbells(MODELS_DIR / "dumbbells.yaml")[bell]
    worst = worst_protrusions(panda, dumbbell, configurations(panda, 8), "panda_quickstart.yaml")
    outside = {label: gap for label, gap in worst.items() if gap > TOLERANCE_M}
    assert not outside, f"geometry outside the planner's spheres [m]: {outside}"
    assert any(label.startswith("panda_hand") for label in worst)  # the hand's shapes are judged too


def test_a_hand_welded_to_the_last_link_is_the_end_effector(panda, tmp_path):
    """end_effector_link names the hand (welded to panda_link7): the identified body is link 7 with
    the hand, and the grasp point given in the hand frame is moved into link 7's frame."""
    assert panda.n == 7 and panda.body_names[panda.end_effector] == "panda_link7"
    flange, tcp = make_panda_urdf.FLANGE_Z, make_panda_urdf.TCP_Z
    np.testing.assert_allclose(panda.extra["grasp_point"], [0, 0, flange + tcp], atol=1e-12)
    hand_mass = make_panda_urdf.hand_inertia()[0]
    assert panda.theta_e[0] == pytest.approx(make_panda_urdf.LINKS[7][0] + hand_mass)
    params = tmp_path / "params.yaml"
    text = PANDA_PARAMS.read_text().replace("urdf: panda.urdf", f"urdf: {MODELS_DIR / 'panda.urdf'}")
    params.write_text(text.replace("end_effector_link: panda_hand", "end_effector_link: no_such_link"))
    with pytest.raises(ModelError, match="params.yaml: end_effector_link: 'no_such_link'"):
        load_robot(params_path=params)


def test_every_panda_link_inertia_is_physically_valid():
    """Franka's link 4 figures break the triangle inequality; the generator's correction is the
    smallest raise of the two smaller principal moments, and every link then passes."""
    for mass, _com, inertia in make_panda_urdf.LINKS:
        moments = np.linalg.eigvalsh(make_panda_urdf.physically_valid(make_panda_urdf._inertia_matrix(inertia)))
        assert moments[0] + moments[1] >= moments[2] and mass > 0
    published = make_panda_urdf._inertia_matrix(make_panda_urdf.LINKS[4][2])
    assert np.linalg.eigvalsh(published)[:2].sum() < np.linalg.eigvalsh(published)[2]


def _random_payload_theta(rng, mass_range, centre, half_extent):
    """A payload the range allows: a few point masses in the box (corners among them)."""
    mass = rng.uniform(*mass_range)
    shares = rng.dirichlet(np.ones(4)) * mass
    theta = np.zeros(10)
    for share in shares:
        unit = rng.uniform(-1, 1, 3) if rng.uniform() < 0.5 else rng.choice([-1.0, 1.0], 3)
        theta += inertial.from_mass_com_inertia(share, np.asarray(centre) + unit * half_extent, np.zeros((3, 3)))
    return theta


def test_a_prior_from_a_payload_range_contains_every_payload_of_the_range(panda):
    """Random payloads in the box (point masses, corners included) are inside the derived prior,
    the nominal too, and a payload with all its mass at the top corner reaches the m c_z bound."""
    rng = np.random.default_rng(1)
    mass_range, centre, half = (0.5, 2.5), panda.extra["grasp_point"], np.array([0.1, 0.05, 0.05])
    nominal, lower, upper = payload_range_prior(panda.theta_e, mass_range, centre_m=centre, half_extent_m=half)
    assert np.all(lower <= nominal) and np.all(nominal <= upper)
    for _ in range(500):
        theta = panda.theta_e + _random_payload_theta(rng, mass_range, centre, half)
        assert np.all(lower - 1e-12 <= theta) and np.all(theta <= upper + 1e-12)
    corner = inertial.from_mass_com_inertia(2.5, centre + half, np.zeros((3, 3)))
    assert panda.theta_e[3] + corner[3] == pytest.approx(upper[3])
    assert panda.theta_e[4] + corner[4] == pytest.approx(upper[4])  # Ixx: y^2 + z^2 at the far corner


def test_the_scenario_derives_the_prior_from_a_payload_range():
    text = "initial_interval: {payload_mass_kg: [0.5, 2.5]}"
    s = load_scenario(SCENARIOS_DIR / "panda_quickstart.yaml", overrides=text)
    assert s.initial_interval.lower[0] == pytest.approx(0.5 + load_robot(params_path=PANDA_PARAMS).theta_e[0])
    both = text[:-1] + ", lower: [1.2, -0.4, -0.4, -1.0, -0.2, -0.2, -0.2, -0.2, -0.2, -0.2]}"
    with pytest.raises(ScenarioError, match=r"initial_interval\.lower: not with payload_mass_kg"):
        load_scenario(SCENARIOS_DIR / "panda_quickstart.yaml", overrides=both)


def test_a_sphere_file_that_leaves_a_shaped_link_out_is_an_error(tmp_path):
    """The planner would not see a link the sphere file omits (the referee would): the error names
    the sphere file, the link and the command that writes the spheres."""
    import yaml
    from safesysid.systems.planner.reachability import arm_spheres

    doc = yaml.safe_load((MODELS_DIR / "panda_spheres.yaml").read_text())
    del doc["links"]["panda_hand"]
    spheres = tmp_path / "spheres.yaml"
    spheres.write_text(yaml.safe_dump(doc))
    params = tmp_path / "params.yaml"
    text = PANDA_PARAMS.read_text().replace("urdf: panda.urdf", f"urdf: {MODELS_DIR / 'panda.urdf'}")
    params.write_text(text.replace("planner_spheres: panda_spheres.yaml", f"planner_spheres: {spheres}"))
    with pytest.raises(ModelError, match=r"spheres.yaml: links: no spheres for panda_hand .*cover_spheres"):
        arm_spheres(load_robot(params_path=params))


@pytest.mark.parametrize(
    "layer, message",
    [
        ("payload: {dumbbell: 8lb}", r"initial_interval: does not contain .*'8lb'.*m 4\.7"),
        ("q0_rad: [0.0, -0.785, 0.0, 0.5, 0.0, 1.571, 0.785]", r"q0_rad: outside the joint limits .*panda_joint4"),
        (
            "obstacles: [{name: in_the_hand, xyz_m: [0.307, 0.0, 0.45], size_m: [0.05, 0.05, 0.05]}]",
            r"q0_rad: the arm touches an obstacle at the start .*in_the_hand",
        ),
    ],
)
def test_a_wrong_set_up_exits_2_naming_the_file_and_the_field(tmp_path, capsys, layer, message):
    """A payload outside the prior, a start outside the limits or in contact: one line, exit 2,
    before anything is simulated."""
    import re

    from safesysid.cli import main

    argv = ["run", str(SCENARIOS_DIR / "panda_quickstart.yaml"), "--scenario-text", layer, "--out", str(tmp_path)]
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "panda_quickstart.yaml" in lines[0] and re.search(message, lines[0]), lines
