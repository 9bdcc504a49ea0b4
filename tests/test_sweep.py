"""`safesysid sweep`: aggregation counts each failure with its seed; trials stream and resume."""

import json

from safesysid.cli import main
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.sweep_cli import aggregate, trial_scene


def _summary(seed, **changes):
    s = {
        "trial_seed": seed,
        "method": "ours",
        "failure": None,
        "collisions": 0,
        "min_clearance_m": 0.1,
        "max_commanded_torque_ratio": 0.5,
        "max_joint_limit_ratio": 0.5,
        "max_velocity_ratio": 0.5,
        "max_tracking_error_ratio": 0.5,
        "contains_truth": True,
        "estimate": {"lower": [0.0] * 10, "upper": [1.0] * 10, "consistent": True},
        "planner": {"missed_deadlines": 0, "brakes": 0},
    }
    s.update(changes)
    return s


def test_aggregate_names_the_seed_of_every_failure():
    trials = [
        _summary(0),
        _summary(1, collisions=3, failure="collision", min_clearance_m=-0.01),
        _summary(2, max_commanded_torque_ratio=1.2, failure="torque_limit"),
        _summary(3, max_tracking_error_ratio=1.01, contains_truth=False, failure="tracking"),
    ]
    agg = aggregate(trials)
    assert agg["trials"] == 4 and agg["collisions"] == 1 and agg["limit_violations"] == 1
    assert agg["tracking_bound_violations"] == 1 and agg["containment_rate"] == 0.75
    assert agg["failures_by_reason"] == {"collision": [1], "torque_limit": [2], "tracking": [3]}
    assert agg["seeds"]["truth_outside"] == [3] and agg["min_clearance_m"] == -0.01
    assert agg["max_commanded_torque_ratio"] == 1.2


def test_trial_scene_is_a_function_of_the_seed_and_adversarial():
    base = load_scenario(SCENARIOS_DIR / "quickstart.yaml")
    a, b = trial_scene(base, 7), trial_scene(base, 7)
    assert a.q0_rad == b.q0_rad and [o.xyz_m for o in a.obstacles] == [o.xyz_m for o in b.obstacles]
    assert a.noise.torque_ratio == a.noise.declared_torque_ratio
    assert a.noise.torque_floor_Nm == a.noise.declared_torque_floor_Nm
    assert trial_scene(base, 8).q0_rad != a.q0_rad


def test_sweep_streams_and_resumes(tmp_path):
    args = ["sweep", str(SCENARIOS_DIR / "quickstart.yaml"), "--workers", "1", "--out", str(tmp_path)]
    assert main(args + ["--trials", "1"]) == 0
    lines = (tmp_path / "trials.jsonl").read_text().splitlines()
    assert len(lines) == 1
    assert main(args + ["--trials", "2"]) == 0  # resumes: runs only the second trial
    seeds = [json.loads(x)["trial_seed"] for x in (tmp_path / "trials.jsonl").read_text().splitlines()]
    assert sorted(seeds) == [0, 1]
    agg = json.loads((tmp_path / "aggregate.json").read_text())
    assert agg["trials"] == 2 and agg["collisions"] == 0 and agg["containment_rate"] == 1.0
    assert "Sweep" in (tmp_path / "report.md").read_text()


def test_sweep_bad_input_exits_2(tmp_path):
    assert main(["sweep", str(SCENARIOS_DIR / "quickstart.yaml"), "--methods", "nope", "--out", str(tmp_path)]) == 2
