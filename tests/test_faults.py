"""Fault injection (scenario `faults`, systems/plant/faults.py): each fault in a short closed loop on
quickstart (one or two plans, 3-4.5 s of simulation). Expected for each: no exception, the
injected fault and the system's reaction in summary.json `events`, no collision or limit
violation on the independent referee, and no published interval that excludes the truth while
`estimate.consistent` is true (published boxes are nested, so the final one decides)."""

import json

import numpy as np
import pytest
from helpers import FULL, assert_safe, event_kinds
from safesysid.online import build_online, run_online
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.systems.config import ScenarioError


def scenario(faults, plans=1, *more):
    return load_scenario(
        SCENARIOS_DIR / "quickstart.yaml", overrides=[f"planner: {{num_plans: {plans}}}", f"faults: {faults}", *more]
    )


def test_bad_fault_options_name_the_field():
    with pytest.raises(ScenarioError, match=r"quickstart.yaml with --scenario-text: faults.sample_nan_rate_per_s"):
        scenario("{sample_nan_rate_per_s: -1.0}")
    with pytest.raises(ScenarioError, match=r"faults.appearing_obstacles\[0\].size_m"):
        scenario("{appearing_obstacles: [{t_s: 1.0, size_m: [0.1, 0.0, 0.1]}]}")
    with pytest.raises(ScenarioError, match=r"faults.planner_failure_kind"):
        scenario("{planner_failure_kind: crash}")


@pytest.mark.parametrize(
    "magnitude, rate, must_detect",
    [
        (20.0, 5.0, True),  # ~40x the declared per-sample bound: the enclosures stop meeting
        (2.0, 50.0, False),  # ~4x, often: absorbed by the integrated noise budget, or detected
    ],
)
def test_torque_sensor_spikes(magnitude, rate, must_detect):
    summary = run_online(
        scenario(f"{{torque_spike_magnitude_Nm: {magnitude}, torque_spike_rate_per_s: {rate}}}"), None, write=False
    )
    print(summary["estimate"], [e for e in summary["events"] if e["kind"] != "fault_torque_spike"])
    assert event_kinds(summary).count("fault_torque_spike") >= 5
    assert_safe(summary, complete=False)
    if must_detect:
        assert not summary["estimate"]["consistent"]


def test_torque_sensor_dropout_is_detected():
    summary = run_online(scenario("{torque_dropout_start_s: 0.5, torque_dropout_duration_s: 0.2}"), None, write=False)
    assert "fault_torque_dropout" in event_kinds(summary)
    assert not summary["estimate"]["consistent"] and "inconsistent_estimate" in event_kinds(summary)
    assert_safe(summary, complete=False)


def test_lost_duplicated_reordered_and_nan_samples(tmp_path):
    """Before the input sanitation both 1.5 s chunks were skipped whole (EstimatorError: NaN /
    time not increasing): 0 updates, the prior published, no event. Now the bad samples are
    rejected or put in place, both updates run and contain the truth."""
    faults = (
        "{sample_drop_rate_per_s: 20.0, sample_duplicate_rate_per_s: 5.0, sample_reorder_rate_per_s: 5.0,"
        " sample_nan_rate_per_s: 2.0}"
    )
    run_online(scenario(faults), tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    found = set(event_kinds(summary))
    for kind in ("fault_sample_dropped", "fault_sample_duplicated", "fault_sample_reordered", "fault_sample_nan"):
        assert kind in found, kind
    for kind in ("sample_gap", "sample_duplicate", "sample_out_of_order", "sample_nonfinite"):
        assert kind in found, kind
    assert summary["sysid"]["updates"] == 2
    assert summary["estimate"]["consistent"] and summary["contains_truth"]
    assert summary["estimate"]["upper"][0] - summary["estimate"]["lower"][0] < 1.0  # identified, not the prior
    assert_safe(summary, complete=False)


@pytest.mark.parametrize("kind", ["timeout"] + (["solver_failed"] if FULL else []))  # one code path
def test_planner_failure_brakes_on_the_verified_plan(kind):
    summary = run_online(
        scenario(f"{{planner_failure_calls: [1], planner_failure_kind: {kind}}}", 2), None, write=False
    )
    events = event_kinds(summary)
    assert "fault_planner" in events and "plan_failed" in events and "brake" in events
    assert summary["planner"]["status"][1] == kind and summary["planner"]["iterations"] == 2
    assert_safe(summary, complete=False)
    assert summary["max_tracking_error_ratio"] <= 1.0 + 1e-9


def test_payload_far_outside_the_prior_is_detected():
    """The truth 0.89 kg above the prior's 5.2 kg: the data's enclosure misses the prior."""
    summary = run_online(scenario("{payload_extra_mass_kg: 3.0}"), None, write=False)
    assert summary["payload_true"]["theta"][0] > 6.0
    assert "fault_payload_heavier" in event_kinds(summary)
    assert not summary["estimate"]["consistent"] and "inconsistent_estimate" in event_kinds(summary)
    assert_safe(summary, complete=False)


def test_payload_just_outside_the_prior_is_flagged():
    """The truth 0.094 kg above the prior's bound: the data's enclosure [4.96, 5.62] kg still
    meets the prior, so no set-membership test can prove A2 false (known limit: the published
    [4.96, 5.2] kg excludes the truth 5.294 kg). The data's best fit lies outside the prior,
    and an event says that the published bound there is the prior's assumption."""
    summary = run_online(scenario("{payload_extra_mass_kg: 2.2}"), None, write=False)
    events = [e for e in summary["events"] if e["kind"] == "estimate_outside_prior"]
    print(summary["estimate"]["lower"][0], summary["estimate"]["upper"][0], events)
    assert events and "m = 5.29" in events[0]["detail"]
    assert summary["collisions"] == 0 and summary["max_commanded_torque_ratio"] <= 1.0 + 1e-9


def test_clipped_velocity_sensor_is_detected():
    """Quickstart's joints peak near 0.03 rad/s; clipped at 0.02 rad/s the estimator's data no
    longer fit any θ in the box (the controller sees the clipped value too)."""
    summary = run_online(scenario("{velocity_clip_rad_s: 0.02}"), None, write=False)
    assert "fault_velocity_clipped" in event_kinds(summary)
    assert not summary["estimate"]["consistent"]
    assert_safe(summary, complete=False)


# -- an obstacle that appears ------------------------------------------------------------------------

DETERMINISTIC = "planner: {max_solve_time_s: 60.0}"  # no wall-time cap hit: the same plan each run


def _executed(scene):
    """(the first plan's PlanResult, the joint positions every 10 ms) of a closed-loop run."""
    from pydrake.systems.analysis import Simulator

    built = build_online(scene)
    sim = Simulator(built.diagram)
    ctx = sim.get_mutable_context()
    built.arm.seed_noise(ctx)
    built.arm.set_state(ctx, np.asarray(scene.q0_rad, float))
    sim.Initialize()
    sim.AdvanceTo(scene.planner.duration_s)
    log = built.loggers["state"].FindLog(ctx)
    q = log.data()[: built.arm.n, ::10].T
    return built.planner.results(built.planner.GetMyContextFromRoot(ctx))[0], q, built.arm


def _box_in_the_margin(plan, q, arm, t_s, depth=0.002, size=0.1):
    """An axis-aligned box reaching `depth` into one certified swept sphere after t_s, whose
    clearance from the planner spheres at every executed configuration (they enclose the link
    shapes) is at least 3 mm: inside the plan's margin, off its actual path."""
    from safesysid.sweeps import _clearance, _sphere_centres
    from safesysid.systems.config import Obstacle

    edges = plan.details["interval_edges_s"]
    centres, radii = plan.details["sphere_centres"], plan.details["sphere_radii"]
    actual = [_sphere_centres(arm.robot, qk, arm.dumbbell) for qk in q]
    for i in np.flatnonzero(edges[:-1] > t_s + 0.2)[::8]:
        for s in np.argsort(radii[i])[::-1]:
            for axis in range(3):
                for sign in (1.0, -1.0):
                    centre = centres[i, s].copy()
                    centre[axis] += sign * (radii[i, s] - depth + size / 2)
                    box = Obstacle(name="appearing", xyz_m=centre.tolist(), size_m=[size] * 3)
                    if box.xyz_m[2] - size / 2 < 0.01:
                        continue  # not through the floor
                    if min(_clearance(c, r, box) for c, r in actual) >= 0.003:
                        return box
    return None


def test_an_obstacle_appearing_in_the_plans_margin_invalidates_it():
    """Appearing at 1.0 s inside plan 0's certified margin (2 mm into its swept spheres), off
    its actual path: the plan is invalidated (no further plan), the robot brakes on it, and the
    events say it is not certified against the new obstacle. The referee holds the obstacle
    from the start."""
    plan, q, arm = _executed(scenario("{}", 1, DETERMINISTIC))
    box = _box_in_the_margin(plan, q, arm, t_s=1.0)
    assert box is not None
    text = f"{{appearing_obstacles: [{{t_s: 1.0, xyz_m: {box.xyz_m}, size_m: {box.size_m}}}]}}"
    summary = run_online(scenario(text, 2, DETERMINISTIC), None, write=False)
    print(summary["events"], summary["min_clearance_m"])
    assert summary["planner"]["solve_time_s"] and summary["planner"]["iterations"] == 1  # no plan through it
    events = {e["kind"]: e for e in summary["events"]}
    assert "obstacle_appeared" in events and "plan_invalidated" in events
    assert "NOT certified" in events["brake"]["detail"]
    assert_safe(summary, complete=False)


def test_an_obstacle_appearing_clear_of_the_plan_is_avoided_by_the_next():
    """Far from the arm: the running plan keeps its certificate, the next plan is certified
    against the new obstacle (it is in the planner's world)."""
    text = "{appearing_obstacles: [{t_s: 0.5, xyz_m: [-0.5, 0.5, 0.3], size_m: [0.2, 0.2, 0.2]}]}"
    built = build_online(scenario(text, 2))
    assert len(built.planner._planner_at(0.6).boxes) == len(built.planner._planner_at(0.4).boxes) + 1
    summary = run_online(scenario(text, 2), None, write=False)
    appeared = [e for e in summary["events"] if e["kind"] == "obstacle_appeared"]
    assert appeared and "clear it by" in appeared[0]["detail"]
    assert "plan_invalidated" not in event_kinds(summary) and summary["planner"]["iterations"] == 2
    assert "estimate_outside_prior" not in event_kinds(summary)  # no false alarm with the truth inside the prior
    assert_safe(summary, complete=False)


def test_after_the_faulty_link_and_the_sanitation_the_estimator_holds_the_clean_samples_in_order(robot):
    """Without simulation: 2000 steps through faults.deliver at high rates (30 % of steps hit),
    then SysIdEstimator._accept with hand-overs every 100 steps: the buffer handed over is exactly
    the true samples that were neither lost nor NaN-corrupted, strictly increasing, none twice."""
    from safesysid.systems.estimation import EstimatorSettings
    from safesysid.systems.estimation.system import SysIdEstimator, SysIdState
    from safesysid.systems.plant.faults import SampleRates, deliver

    n, h = robot.n, 0.001
    est = SysIdEstimator(robot, EstimatorSettings(), h, 0.1, (np.zeros(10), np.ones(10)), np.full(10, 0.5))
    rates = SampleRates(drop=0.1, duplicate=0.1, reorder=0.1, nan=0.05)
    rng = np.random.default_rng(7)
    run, held, handed, expected, kinds_seen = SysIdState(None), None, [], [], set()
    for k in range(2000):
        row = np.concatenate([[k * h], rng.normal(size=3 * n)])
        rows, held, events = deliver(row, held, rng.uniform(size=5), rates=rates, n=n)
        kinds_seen.update(e["kind"] for e in events)
        expected += [r[0] for r in rows if np.all(np.isfinite(r))]
        for r in rows:
            run = est._accept(run, r)
        if k % 100 == 99:  # hand over, as an update does
            handed += [r[0] for r in run.samples]
            run = SysIdState(None, (), (), run.samples[-1][0] if run.samples else run.handed_t, run.input_issues)
    handed += [r[0] for r in run.samples]
    assert kinds_seen == {
        "fault_sample_dropped",
        "fault_sample_duplicated",
        "fault_sample_reordered",
        "fault_sample_nan",
    }
    assert np.all(np.diff(handed) > 0)
    late = sorted(set(expected) - set(handed))  # reordered across a hand-over: rejected, and said so
    assert handed == sorted(set(expected) - set(late))
    issues = {kind for _, kind, _ in run.input_issues}
    assert {"sample_nonfinite", "sample_duplicate", "sample_out_of_order"} <= issues
    assert len(late) == sum(d.startswith("rejected (older") for _, _, d in run.input_issues)
