"""Closed loop (Algorithm 2) on a real arm whose own parameters are drawn inside the declared
box (issue 11, item 5): links, friction, armature and torque offsets at a random vertex
("corner") or uniform inside ("drawn"), while the controller, planner and estimator keep the
nominal model and the box. CI: one corner run; SAFESYSID_FULL=1: 20 random scenes."""

import numpy as np
import pytest
from helpers import FULL, n_trials
from safesysid.online import run_online
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.sweeps import random_scene


@pytest.fixture(scope="module")
def quickstart():
    return load_scenario(SCENARIOS_DIR / "quickstart.yaml")


@pytest.mark.parametrize("index", range(n_trials(1, 20)))
def test_closed_loop_with_drawn_robot_parameters(quickstart, index):
    scene = random_scene(quickstart, np.random.default_rng(3000 + index)) if FULL else quickstart
    scene.plant.robot_parameters = "corner" if index % 2 == 0 else "drawn"
    scene.seed = 1 + index
    summary = run_online(scene, None, method="ours", write=False)
    assert summary["collisions"] == 0 and summary["max_torque_ratio"] <= 1.0 + 1e-9
    assert summary["max_joint_limit_ratio"] <= 1.0 and summary["max_velocity_ratio"] <= 1.0
    assert summary["max_tracking_error_ratio"] <= 1.0 + 1e-9
    assert summary["contains_truth"], summary["estimate"]
    assert summary["estimate"]["consistent"] is True and summary["events"] == [], summary["events"]
    assert summary["sysid"]["updates"] >= 4
