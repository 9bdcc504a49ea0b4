import numpy as np
import pytest

from safesysid.scenario import SCENARIOS_DIR, ScenarioError, load_scenario, robot_from_scenario


def test_defaults_and_robot():
    s = load_scenario()
    assert s.planner.duration_s == 3.0 and s.planner.replan_period_s == 1.5
    robot = robot_from_scenario(s)
    assert robot.n == len(s.q0_rad) and robot.coulomb_smoothing == s.robot.coulomb_smoothing_rad_s


@pytest.mark.parametrize("text, field", [
    ("planner: {duraton_s: 3}", "planner.duraton_s"),
    ("planner: {duration_s: fast}", "planner.duration_s"),
    ("obstacles: [{xyz_m: [1, 2]}]", "obstacles[0].xyz_m"),
    ("method: best", "method"),
    ("robot: {params: nowhere.yaml}", "robot.params"),
    ("initial_interval: {lower: [0]}", "initial_interval.lower"),
    ("task: {goal_q_rad: [0, 1]}", "task.goal_q_rad"),
    ("task: {place_xyz_m: [0.3, 0.0]}", "task.place_xyz_m"),
    ("task: {goal_q_rad: [0, 0, 0, 0, 0, 0, 0], place_xyz_m: [0.3, 0.0, 0.2]}", "task: give"),
    ("obstacles: [{name: box}]\ntask: {platform: table}", "task.platform"),
    ("task: {solver: cplex}", "task.solver"),
    ("plant: {time_step_s: 0.01}", "plant.time_step_s"),
    ("task: {placement_tolerance_m: 0}", "task.placement_tolerance_m"),
    ("task: {torque_margin_ratio: 1.0}", "task.torque_margin_ratio"),
    ("task: {place_xyz_m: [0.3, 0.0, 0.2], payload_model: 9lb}", "task.payload_model"),
])
def test_bad_keys_are_named_with_the_file(tmp_path, text, field):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    msg = str(err.value)
    assert str(path) in msg and field in msg and "\n" not in msg


def test_invalid_yaml_and_missing_file(tmp_path):
    with pytest.raises(ScenarioError, match="missing.yaml"):
        load_scenario(tmp_path / "missing.yaml")
    path = tmp_path / "broken.yaml"
    path.write_text("planner: [1, 2\n")
    with pytest.raises(ScenarioError, match="invalid YAML"):
        load_scenario(path)


def test_shipped_scenarios_load():
    files = sorted(SCENARIOS_DIR.glob("*.yaml"))
    for path in files:
        s = load_scenario(path)
        assert len(s.q0_rad) == 7 and np.all(np.isfinite(s.q0_rad))
