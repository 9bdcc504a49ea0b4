"""Pruning with physical knowledge (issue 15): the density-realizability LMI of a payload inside a
bounding volume, solved from outside by certified cutting-plane LPs (estimation/physical.py).

Outer bound: truths are drawn as point masses INSIDE the volume, many ON its surface (corners of
the box, points of the ellipsoid's surface: the boundary the LMI's proof uses), the gripper's own
parameters anywhere in its box, and the data box touches the truth on a random side per parameter
(the truth on the box's boundary). Power: a payload outside the volume is cut out.
"""

import numpy as np
import pytest
from helpers import n_trials
from safesysid.systems.estimation.physical import prune_box
from safesysid.systems.estimation.settings import BoundingVolume, rpy_matrix
from safesysid.systems.model import inertial
from safesysid.systems.model.uncertainty import parameter_radius

PRIOR_HALF = np.array([2.0, 0.4, 0.4, 0.45] + [0.2] * 6)  # Table II half-widths


def volume(shape, rng):
    return BoundingVolume(
        shape,
        np.array([0.0, 0.0, -0.2]) + rng.uniform(-0.02, 0.02, 3),
        rng.uniform([0.08, 0.04, 0.04], [0.12, 0.06, 0.06]),
        rpy_matrix(rng.uniform(-0.5, 0.5, 3)),
    )


def surface_points(vol, rng, k):
    """k points of the volume, on its surface (box: corners and faces; ellipsoid: the sphere image)."""
    u = rng.normal(size=(k, 3))
    if vol.shape == "ellipsoid":
        u /= np.linalg.norm(u, axis=1, keepdims=True)
    else:
        u = np.clip(u / np.abs(u).max(1, keepdims=True), -1, 1)
        u[: k // 2] = np.sign(u[: k // 2])  # corners
    return vol.centre_m + (u * vol.half_extent_m) @ vol.R.T


def payload_theta(points, masses):
    return sum(inertial.from_mass_com_inertia(m, p, np.zeros((3, 3))) for p, m in zip(points, masses))


def gripper(robot):
    rad = parameter_radius(robot, 0.05, 0.05)[robot.ee_slice]
    return robot.theta_e - rad, robot.theta_e + rad


@pytest.mark.parametrize("shape", ["box", "ellipsoid"])
def test_pruning_never_cuts_a_payload_inside_the_volume(robot, shape):
    g_lo, g_hi = gripper(robot)
    for trial in range(n_trials(8, 60)):
        rng = np.random.default_rng(1500 + trial)
        vol = volume(shape, rng)
        k = int(rng.integers(1, 7))
        pts = surface_points(vol, rng, k)
        pts[k // 2 :] = vol.centre_m + (pts[k // 2 :] - vol.centre_m) * rng.uniform(0, 1, (k - k // 2, 1))
        assert np.all(vol.contains(pts - 1e-12 * (pts - vol.centre_m)))
        theta_g = robot.theta_e * rng.uniform(0.95, 1.05)  # a consistent gripper inside its box
        assert np.all((g_lo <= theta_g) & (theta_g <= g_hi))
        truth = theta_g + payload_theta(pts, rng.uniform(0.1, 2.0, k))
        side = rng.integers(0, 3, 10)  # truth on the lower side, the upper side, or inside
        lo = truth - np.where(side == 0, 0.0, rng.uniform(0, 1, 10) * PRIOR_HALF)
        hi = truth + np.where(side == 1, 0.0, rng.uniform(0, 1, 10) * PRIOR_HALF)
        p_lo, p_hi, feasible = prune_box(lo, hi, volume=vol, gripper=(g_lo, g_hi))
        assert feasible
        assert np.all((p_lo <= truth) & (truth <= p_hi)), (trial, truth, p_lo, p_hi)
        assert np.all((lo <= p_lo) & (p_hi <= hi))


def test_pruning_cuts_a_payload_outside_the_volume_and_shrinks_the_inertias(robot):
    rng = np.random.default_rng(3)
    vol = BoundingVolume("box", np.array([0.0, 0.0, -0.2]), np.array([0.1, 0.05, 0.05]), np.eye(3))
    g = gripper(robot)
    inside = robot.theta_e + payload_theta(surface_points(vol, rng, 4), [0.5, 0.5, 0.4, 0.4])
    lo, hi = inside - PRIOR_HALF / 2, inside + PRIOR_HALF / 2
    p_lo, p_hi, feasible = prune_box(lo, hi, volume=vol, gripper=g)
    assert feasible
    shrink = (p_hi - p_lo)[4:] / (hi - lo)[4:]
    # Measured: the rotational inertias keep 0.16-0.78 of their width (mean 0.45) here.
    assert shrink.max() < 0.85 and shrink.mean() < 0.6, shrink
    # The same mass 0.25 m outside the box: its second moments are out of reach of the volume.
    outside = robot.theta_e + payload_theta(np.array([[0.0, 0.0, -0.45]]), [1.8])
    o_lo, o_hi, feasible = prune_box(outside - 1e-3, outside + 1e-3, volume=vol, gripper=g)
    assert not feasible or not np.all((o_lo <= outside) & (outside <= o_hi))


def test_consistency_alone_prunes_and_keeps_the_truth(robot, dumbbells):
    from safesysid.systems.model.payload import payload_theta_in_end_effector

    truth = robot.theta_e + payload_theta_in_end_effector(dumbbells["8lb"], robot.extra["grasp_point"])
    lo, hi = truth - PRIOR_HALF / 4, truth + PRIOR_HALF / 4
    lo[0], hi[0] = truth[0] - 0.05, truth[0] + 0.05
    p_lo, p_hi, feasible = prune_box(lo, hi)
    assert feasible and np.all((p_lo <= truth) & (truth <= p_hi))
    assert np.any(p_hi - p_lo < 0.9 * (hi - lo))


@pytest.fixture(scope="module")
def log8(robot, dumbbells):
    """3 s of an 8 lb payload moved 0.3 rad per joint, noise inside the declared bound."""
    from test_estimator_prior import payload_log

    return payload_log(robot, dumbbells["8lb"], 21, 0.3)


def pruning_estimator(robot, volume):
    from helpers import PRIOR, PRIOR_NOMINAL
    from safesysid.systems import estimation as E

    settings = E.EstimatorSettings(physical_pruning=True, payload_volume=volume)
    return E.IncrementalEstimator(robot, settings=settings, prior=PRIOR, prior_nominal=PRIOR_NOMINAL)


def test_estimator_reports_the_data_box_and_the_pruned_box_separately(robot, log8):
    t, q, v, tau, truth = log8
    vol = BoundingVolume("box", np.array([0.0, 0.0, -0.2]), np.array([0.11, 0.055, 0.055]), np.eye(3))
    est = pruning_estimator(robot, vol)
    for k in range(0, len(t), 1500):
        est.add(t[k : k + 1500], q[k : k + 1500], v[k : k + 1500], tau[k : k + 1500])
        e = est.update()
        assert e.consistent and e.contains(truth)
        assert np.all((e.data_lower <= truth) & (truth <= e.data_upper))
        assert np.all((e.data_lower <= e.lower) & (e.upper <= e.data_upper))
    # Prior knowledge shrinks the inertias (measured: 1.61 -> 0.53 kg·m² of summed width).
    data_widths = (e.data_upper - e.data_lower)[4:]
    assert np.all(e.widths[4:] < data_widths) and e.widths[4:].sum() < 0.5 * data_widths.sum()


def test_a_payload_outside_the_declared_volume_latches_inconsistency(robot, log8):
    """The volume is an assumption (A9): data that contradict it are flagged, the box is kept."""
    t, q, v, tau, truth = log8
    wrong = BoundingVolume("ellipsoid", np.array([0.0, 0.0, 0.3]), np.array([0.02, 0.02, 0.02]), np.eye(3))
    est = pruning_estimator(robot, wrong)
    est.add(t, q, v, tau)
    e = est.update()
    assert not e.consistent and "physical knowledge" in e.message
    assert e.contains(truth)  # the prior, published unchanged


@pytest.mark.parametrize("scenario, payloads", [("identify_all.yaml", None), ("one_of_everything.yaml", ["5lb"])])
def test_scenario_volumes_contain_their_dumbbells(robot, dumbbells, scenario, payloads):
    """A9 in the simulation: identify_all.yaml's box holds each 4-8 lb dumbbell, one_of_everything's
    ellipsoid its 5 lb one (every cylinder's rim points), so their LMI holds for the simulated payload."""
    from safesysid.scenario import SCENARIOS_DIR, load_scenario
    from safesysid.systems.estimation.settings import payload_volume
    from safesysid.systems.model.payload import payload_theta_in_end_effector

    vol = payload_volume(load_scenario(SCENARIOS_DIR / scenario).payload.bounding_volume)
    grasp = robot.extra["grasp_point"]
    angle = np.linspace(0, 2 * np.pi, 64)
    for name, db in dumbbells.items():
        if payloads is not None and name not in payloads:
            continue
        for _, x, r, length in db.parts():
            for end in (x - length / 2, x + length / 2):
                rim = np.stack([np.full_like(angle, end), r * np.cos(angle), r * np.sin(angle)], 1)
                assert np.all(vol.contains(rim + grasp)), name  # handle along the end-effector x axis
        j = inertial.pseudo_inertia(payload_theta_in_end_effector(db, grasp))
        assert all(np.trace(j @ Q) >= 0 for Q in vol.forms())


@pytest.mark.parametrize(
    "text, field",
    [
        ("payload: {bounding_volume: {shape: cube}}", "payload.bounding_volume.shape"),
        ("payload: {bounding_volume: {shape: box, half_extent_m: [0.1, 0.0, 0.1]}}", "half_extent_m"),
        ("payload: {bounding_volume: {shape: ellipsoid, centre_m: [0.0, 0.0]}}", "centre_m"),
    ],
)
def test_a_bad_bounding_volume_is_refused_naming_the_field(text, field):
    from safesysid.scenario import SCENARIOS_DIR, load_scenario
    from safesysid.systems.config import ScenarioError

    with pytest.raises(ScenarioError, match=field):
        load_scenario(SCENARIOS_DIR / "identify_all.yaml", overrides=[text])
