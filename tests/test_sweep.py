"""`safesysid sweep`: aggregation counts each failure with its seed; trials stream to trials.jsonl,
survive a kill (SIGTERM halfway) and resume with nothing lost or duplicated; a report line
replays a trial exactly; Ray tasks give the pool's results for the same seeds."""

import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from safesysid.cli import main
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.sweep_cli import aggregate, read_trials, trial_scene
from test_determinism import without_wall_time
from threadpoolctl import threadpool_limits

SCENARIO = str(SCENARIOS_DIR / "quickstart.yaml")
SHORT = ["--scenario-text", "planner: {num_plans: 2}"]  # CI size: 4.5 s of simulation per trial
TRIALS = 4
TRIAL_FIELDS = ("trial_seed", "replay_scenario_text", "obstacles", "q0_rad")  # the sweep's additions


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


def _by_trial(path):
    return {(s["method"], s["trial_seed"]): s for s in read_trials(Path(path) / "trials.jsonl")}


def _comparable(summary):
    return json.dumps(without_wall_time({k: v for k, v in summary.items() if k not in TRIAL_FIELDS}), sort_keys=True)


def test_aggregate_names_the_seed_of_every_failure():
    trials = [
        _summary(0),
        _summary(1, collisions=3, failure="collision", min_clearance_m=-0.01),
        _summary(2, max_commanded_torque_ratio=1.2, failure="torque_limit"),
        _summary(3, max_tracking_error_ratio=1.01, contains_truth=False, failure="tracking"),
        {"trial_seed": 4, "method": "ours", "success": False, "failure": "error", "error": "ValueError: x"},
    ]
    agg = aggregate(trials)
    assert agg["trials"] == 5 and agg["errors"] == 1 and agg["collisions"] == 1 and agg["limit_violations"] == 1
    assert agg["tracking_bound_violations"] == 1 and agg["containment_rate"] == 0.75
    assert agg["failures_by_reason"] == {"collision": [1], "error": [4], "torque_limit": [2], "tracking": [3]}
    assert agg["seeds"]["truth_outside"] == [3] and agg["min_clearance_m"] == -0.01
    assert agg["max_commanded_torque_ratio"] == 1.2
    assert agg["width_per_parameter"]["m"] == {"median": 1.0, "p90": 1.0}


def test_trial_scene_is_a_function_of_the_seed_and_adversarial():
    base = load_scenario(SCENARIOS_DIR / "quickstart.yaml")
    a, b = trial_scene(base, 7), trial_scene(base, 7)
    assert a.q0_rad == b.q0_rad and [o.xyz_m for o in a.obstacles] == [o.xyz_m for o in b.obstacles]
    assert a.noise.torque_ratio == a.noise.declared_torque_ratio
    assert a.noise.torque_floor_Nm == a.noise.declared_torque_floor_Nm
    assert trial_scene(base, 8).q0_rad != a.q0_rad


def test_read_trials_drops_a_cut_line_and_a_repeat(tmp_path):
    path = tmp_path / "trials.jsonl"
    good = [json.dumps(_summary(k)) for k in range(2)]
    path.write_text(good[0] + "\n" + good[1] + "\n" + good[0] + "\n" + good[1][:25])  # killed mid-write
    assert [s["trial_seed"] for s in read_trials(path)] == [0, 1]
    assert path.read_text() == good[0] + "\n" + good[1] + "\n"  # the next append starts a fresh line


def _workers_alive(marker):
    """Processes whose command line names `marker` (the forked pool workers share the sweep's)."""
    alive = []
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and marker in (proc / "cmdline").read_bytes().decode(errors="replace"):
                alive.append(int(proc.name))
        except OSError:
            continue
    return alive


@pytest.fixture(scope="module")
def pool_sweep(tmp_path_factory):
    """A 4-trial pool sweep killed by SIGTERM after its first trial, then resumed in the same DIR:
    (DIR, the lines on disk at the kill, the exit code of the killed run)."""
    out = tmp_path_factory.mktemp("pool") / "sweep"
    cmd = [sys.executable, "-m", "safesysid.cli", "sweep", SCENARIO, "--trials", str(TRIALS), "--workers", "2"]
    proc = subprocess.Popen([*cmd, *SHORT, "--out", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    jsonl = out / "trials.jsonl"
    while not (jsonl.exists() and jsonl.read_text().count("\n") >= 1):
        assert proc.poll() is None, "the sweep ended before its first trial"
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    code = proc.wait(timeout=60)
    at_kill = jsonl.read_text().splitlines()
    deadline = time.monotonic() + 10
    while _workers_alive(str(out)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not _workers_alive(str(out)), "pool workers outlived the killed sweep"
    assert main(["sweep", SCENARIO, "--trials", str(TRIALS), "--workers", "2", *SHORT, "--out", str(out)]) == 0
    return out, at_kill, code


def test_sweep_killed_halfway_resumes_with_nothing_lost_or_duplicated(pool_sweep):
    out, at_kill, code = pool_sweep
    assert code == 1 and 1 <= len(at_kill) < TRIALS  # interrupted halfway, told so
    lines = (out / "trials.jsonl").read_text().splitlines()
    assert lines[: len(at_kill)] == at_kill  # nothing lost ...
    assert sorted(json.loads(x)["trial_seed"] for x in lines) == list(range(TRIALS))  # ... or duplicated
    agg = json.loads((out / "aggregate.json").read_text())
    assert agg["trials"] == TRIALS and agg["complete"] and agg["trials_run"] == TRIALS - len(at_kill)
    assert agg["collisions"] == agg["limit_violations"] == agg["tracking_bound_violations"] == 0
    assert agg["containment_rate"] == 1.0 and agg["planner_budget"] == "iterations"
    assert set(agg["width_per_parameter"]) >= {"m", "Ixz"} and agg["trials_per_minute"] > 0
    assert "trials/min" in (out / "report.md").read_text()


def test_a_report_line_replays_the_trial_exactly(pool_sweep, tmp_path):
    """`safesysid run` with the trial's --scenario-text gives its summary (other process, BLAS threads)."""
    from safesysid.sweep_cli import replay_command

    out, _, _ = pool_sweep
    trial = _by_trial(out)[("ours", 1)]
    argv = shlex.split(replay_command(SCENARIO, trial, [SHORT[1]]))
    assert argv[:2] == ["safesysid", "run"]
    # Threaded BLAS here even in an xdist worker (conftest.py sets one thread there): the pool's
    # trials ran single-threaded, and the replay must not depend on it.
    with threadpool_limits(limits=max(2, os.cpu_count() or 2), user_api="blas"):
        assert main([*argv[1:], "--out", str(tmp_path)]) == 0
    replayed = json.loads((tmp_path / "summary.json").read_text())
    assert _comparable(replayed) == _comparable(trial)


def test_ray_tasks_give_the_pool_results(pool_sweep, tmp_path):
    ray = pytest.importorskip("ray")
    out, _, _ = pool_sweep
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        args = ["sweep", SCENARIO, "--trials", str(TRIALS), "--ray", *SHORT, "--out", str(tmp_path)]
        assert main(args) == 0
        assert main(args) == 0  # resumes: nothing left to run
    finally:
        ray.shutdown()
    ray_trials, pool_trials = _by_trial(tmp_path), _by_trial(out)
    assert len((tmp_path / "trials.jsonl").read_text().splitlines()) == TRIALS
    assert sorted(ray_trials) == sorted(pool_trials) == [("ours", k) for k in range(TRIALS)]
    for key, summary in ray_trials.items():
        assert _comparable(summary) == _comparable(pool_trials[key]), key
    assert json.loads((tmp_path / "aggregate.json").read_text())["executor"] == "ray (local)"


def test_sweep_bad_input_exits_2(tmp_path):
    assert main(["sweep", SCENARIO, "--methods", "nope", "--out", str(tmp_path)]) == 2
    assert main(["sweep", SCENARIO, "--workers", "0", "--out", str(tmp_path)]) == 2
