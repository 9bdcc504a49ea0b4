"""The guarantees on both shipped arms: the Kinova Gen3 and the Franka Panda (models/), each in
one adversarial closed-loop scene (Algorithm 2): noise at the declared bound, the real arm's
parameters at a corner of their box. Judged by the referee (link shapes vs obstacles, commanded
torque before saturation, the certified tube) and the truth inside the published interval.
CI: two plans per arm; SAFESYSID_FULL=1: the full identification phase on 5 random scenes each."""

import numpy as np
import pytest
from helpers import FULL, n_trials
from safesysid.online import run_online
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.sweeps import random_scene

ARMS = {"gen3": "quickstart.yaml", "panda": "panda_quickstart.yaml"}


@pytest.mark.parametrize("index", range(n_trials(1, 5)))
@pytest.mark.parametrize("arm", ARMS)
def test_the_guarantees_hold_on_each_arm(arm, index):
    scene = load_scenario(SCENARIOS_DIR / ARMS[arm])
    if FULL:
        scene = random_scene(scene, np.random.default_rng(4000 + index), near_clearance_m=(0.01, 0.05))
    else:
        scene.planner.num_plans = 2
    scene.noise.torque_ratio = scene.noise.declared_torque_ratio
    scene.noise.torque_floor_Nm = scene.noise.declared_torque_floor_Nm
    scene.plant.robot_parameters = "corner"
    scene.seed = 7 + index
    summary = run_online(scene, None, method="ours", write=False)
    assert summary["collisions"] == 0 and summary["min_clearance_m"] > 0
    assert summary["max_commanded_torque_ratio"] <= 1.0 + 1e-9  # before saturation
    assert summary["max_joint_limit_ratio"] <= 1.0 and summary["max_velocity_ratio"] <= 1.0
    assert summary["max_tracking_error_ratio"] <= 1.0 + 1e-9
    assert summary["contains_truth"], summary["estimate"]
    assert summary["success"], (summary["failure"], summary["events"])
