import numpy as np
import pytest
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.systems.config import ScenarioError
from safesysid.systems.model.loading import robot_from_scenario


def test_defaults_and_robot():
    s = load_scenario()
    assert s.planner.duration_s == 3.0 and s.planner.replan_period_s == 1.5
    robot = robot_from_scenario(s)
    assert robot.n == len(s.q0_rad) and robot.coulomb_smoothing == s.robot.coulomb_smoothing_rad_s


@pytest.mark.parametrize(
    "text, field",
    [
        ("planner: {duraton_s: 3}", "planner.duraton_s"),
        ("planner: {duration_s: fast}", "planner.duration_s"),
        ("planner: {refinement_scale: 0}", "planner.refinement_scale"),
        ("planner: {continuation: true}", "planner.continuation"),
        ("planner: {exciting_weighting: noise}\nnoise: {declared_torque_floor_Nm: 0.0}", "planner.exciting_weighting"),
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
        ("estimator: {torque_lag_s: [0.12, 0.1]}", "estimator.torque_lag_s"),
        ("estimator: {torque_lag_s: [-0.01, 0.1]}", "estimator.torque_lag_s"),
        ("estimator: {torque_lag_s: [0.1]}", "estimator.torque_lag_s"),
        ("estimator: {torque_lag_s: -0.1}", "estimator.torque_lag_s"),
    ],
)
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
        assert len(s.q0_rad) == robot_from_scenario(s).n and np.all(np.isfinite(s.q0_rad))


def test_layers_merge_deeply_the_drake_way(tmp_path):
    """A layer changes only the keys it names (yaml_load_typed(defaults=previous)): the old
    shallow `raw.update(overrides)` reset noise.torque_ratio to its default 0.025 here."""
    path = tmp_path / "s.yaml"
    path.write_text("noise: {torque_ratio: 0.03}\nplanner: {num_plans: 2}\nobstacles: [{name: a}, {name: b}]\n")
    for override in ({"noise": {"torque_floor_Nm": 0.1}}, "noise: {torque_floor_Nm: 0.1}"):
        s = load_scenario(path, overrides=override)
        assert (s.noise.torque_ratio, s.noise.torque_floor_Nm) == (0.03, 0.1)
        assert s.planner.num_plans == 2 and [o.name for o in s.obstacles] == ["a", "b"]
    # Later layers win; a list is replaced whole (Drake's convention for sequences).
    s = load_scenario(
        path,
        overrides=["noise: {torque_floor_Nm: 0.1}", {"noise": {"torque_floor_Nm": 0.2}, "obstacles": [{"name": "c"}]}],
    )
    assert (s.noise.torque_ratio, s.noise.torque_floor_Nm) == (0.03, 0.2)
    assert [o.name for o in s.obstacles] == ["c"]
    # The schema's defaults are not touched by a layer.
    assert load_scenario().noise.torque_ratio == 0.025


@pytest.mark.parametrize(
    "text, where, field",
    [
        ("noise: {torque_rato: 0.1}", "--scenario-text:", "noise.torque_rato"),
        ("noise: [1", "--scenario-text: line 1", "invalid YAML"),
        ("method: best", "with --scenario-text", "method"),
    ],
)
def test_bad_layer_is_named(tmp_path, text, where, field):
    path = tmp_path / "s.yaml"
    path.write_text("seed: 1\n")
    with pytest.raises(ScenarioError) as err:
        load_scenario(path, overrides=text)
    msg = str(err.value)
    assert where in msg and field in msg and "\n" not in msg


def _leaf_keys(schema, prefix=""):
    import dataclasses
    import typing

    for f in dataclasses.fields(schema):
        if f.name == "source":
            continue
        kind = typing.get_type_hints(schema)[f.name]
        if dataclasses.is_dataclass(kind):
            yield from _leaf_keys(kind, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}"


def test_one_of_everything_names_every_field_and_every_effect():
    import dataclasses

    import yaml
    from safesysid.systems.config import PlantEffects, Scenario

    raw = yaml.safe_load((SCENARIOS_DIR / "one_of_everything.yaml").read_text())
    for key in _leaf_keys(Scenario):
        node = raw
        for part in key.split("."):
            assert part in node, f"one_of_everything.yaml lacks {key}"
            node = node[part]
    s = load_scenario(SCENARIOS_DIR / "one_of_everything.yaml")
    for f in dataclasses.fields(PlantEffects):
        assert getattr(s.plant.effects, f.name) != getattr(PlantEffects(), f.name), f"effect {f.name} is off"
    assert s.plant.robot_parameters == "drawn" and s.task.platform


SMOKE = [(p.name, None) for p in sorted(SCENARIOS_DIR.glob("*.yaml")) if p.name != "one_of_everything.yaml"]
SMOKE += [("one_of_everything.yaml", kind) for kind in ("armour", "pid", "adaptive", "adaptive_robust")]


@pytest.mark.parametrize("name, kind", SMOKE)
def test_every_scenario_builds_and_simulates_10_ms(name, kind):
    """Drake-style smoke test: the closed-loop diagram of every shipped scenario (and of
    one_of_everything.yaml with each controller kind) is built and simulated for 10 ms."""
    from pydrake.systems.analysis import Simulator
    from safesysid.online import build_online

    s = load_scenario(SCENARIOS_DIR / name, overrides=f"controller: {{kind: {kind}}}" if kind else None)
    built = build_online(s)
    sim = Simulator(built.diagram)
    ctx = sim.get_mutable_context()
    built.arm.set_state(ctx, np.asarray(s.q0_rad, float))
    sim.Initialize()
    sim.AdvanceTo(0.01)
    state = built.loggers["state"].FindLog(ctx).data()
    assert ctx.get_time() == pytest.approx(0.01) and state.shape[1] >= 10 and np.all(np.isfinite(state))
    assert built.monitor.record(built.monitor.GetMyContextFromRoot(ctx)).summary()["collisions"] == 0
