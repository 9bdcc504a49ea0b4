"""Closed-loop Algorithm 2 on the simulated real arm: safety on the true geometry (link shapes,
not the planner's spheres), the controller's command before saturation, joint and velocity
limits, the tracking tube, interval containment; methods and outputs. The random scenes put a box
1-5 cm outside the planner's spheres at the start (adversarially close). Full sample:
SAFESYSID_FULL=1 (100 scenes)."""

import json

import numpy as np
import pytest
from helpers import FULL, assert_safe, n_trials, simulate_online
from safesysid.online import run_online
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.sweeps import random_scene


@pytest.fixture(scope="module")
def quickstart():
    return load_scenario(SCENARIOS_DIR / "quickstart.yaml")


def test_quickstart_outputs(quickstart, tmp_path):
    summary = run_online(quickstart, tmp_path, method="ours")
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    for key in (
        "scenario",
        "method",
        "seed",
        "success",
        "failure",
        "collisions",
        "min_clearance_m",
        "max_torque_ratio",
        "max_joint_limit_ratio",
        "max_tracking_error_rad",
        "tracking_bound_rad",
        "payload_true",
        "estimate",
        "contains_truth",
        "cond_Y",
        "planner",
        "sysid",
        "wall_time_s",
        "sim_time_s",
        "max_commanded_torque_ratio",
        "events",
    ):
        assert key in on_disk
    assert (tmp_path / "replay.html").stat().st_size > 100_000 and (tmp_path / "log.csv").exists()
    assert_safe(summary)
    assert summary["planner"]["iterations"] >= 1 and summary["sysid"]["updates"] >= 4
    robust = summary["robust_input"]["identification"]  # ARMOUR's robust term, from its diagnostics
    assert 0 < robust["max_w_bar_Nm"] and robust["min_h_J"] <= quickstart.controller.V_max
    assert (robust["active_fraction"] > 0) == (robust["max_lambda_Nm"] > 0)
    est = summary["estimate"]
    assert est["upper"][0] - est["lower"][0] < 4.0  # tightened from Table II's [1.2, 5.2]
    # The run's log is a valid joint log: Algorithm 1 offline on it contains the truth too.
    from safesysid.cli import main

    assert (
        main(
            [
                "sysid",
                str(tmp_path / "log.csv"),
                "--scenario",
                str(SCENARIOS_DIR / "quickstart.yaml"),
                "--out",
                str(tmp_path / "sysid"),
            ]
        )
        == 0
    )
    offline = json.loads((tmp_path / "sysid" / "estimate.json").read_text())
    truth = np.array(summary["payload_true"]["theta"])
    lower, upper = np.array(offline["lower"]), np.array(offline["upper"])
    assert np.all((lower <= truth) & (truth <= upper))


def test_robust_input_summary_splits_the_armour_steps_by_phase():
    from safesysid.summary import robust_input_summary

    # rows [V_bar, h, lambda, |r|, |w_bar|]; ARMOUR runs steps 0-3 (identification 0-1, task 2-3)
    diag = np.array([[0, 0.02, 0, 0, 5], [0, 0.01, 2, 0, 6], [0, 0.03, 0, 0, 1], [0, 0.04, 0, 0, 2], [0, -1, 9, 0, 9]])
    armour = np.array([True, True, True, True, False])
    out = robust_input_summary(diag, armour, np.array([True, True, False, False, False]))
    assert out["identification"] == {"active_fraction": 0.5, "max_lambda_Nm": 2.0, "min_h_J": 0.01, "max_w_bar_Nm": 6.0}
    assert out["task"] == {"active_fraction": 0.0, "max_lambda_Nm": 0.0, "min_h_J": 0.03, "max_w_bar_Nm": 2.0}
    assert robust_input_summary(diag, np.zeros(5, bool), np.ones(5, bool)) == {}


@pytest.mark.parametrize("index", range(n_trials(2, 100)))
def test_random_scenes_with_a_box_close_to_the_arm_are_safe(quickstart, index):
    # 4-6 cm: just outside the certified swept spread of the V_max 0.02 J tube (3.2-3.8 cm), so the
    # first plan can start and must pass the box; closer boxes leave the arm at rest (planner_infeasible)
    scene = random_scene(quickstart, np.random.default_rng(1000 + index), near_clearance_m=(0.04, 0.06))
    assert scene.obstacles and scene.obstacles[0].name == "near"
    summary = run_online(scene, None, method="ours", write=False)
    print(
        {
            k: summary[k]
            for k in (
                "min_clearance_m",
                "max_commanded_torque_ratio",
                "max_joint_limit_ratio",
                "max_velocity_ratio",
                "max_tracking_error_ratio",
                "contains_truth",
            )
        },
        summary["events"],
    )
    assert_safe(summary)
    assert summary["robot_parameters"] == "drawn"  # measured with the arm's parameters drawn in their box (A1)
    assert "solved" in summary["planner"]["status"] or "best_feasible" in summary["planner"]["status"]  # it moved
    assert summary["min_clearance_m"] < 0.1  # the referee sees the box close to the real geometry


@pytest.mark.skipif(
    not FULL,
    reason="a statistical claim: 20 pairs (SAFESYSID_FULL=1); CI checks the planner's cond(W) in tests/test_planner.py",
)
def test_exciting_plans_beat_random_ones(quickstart):
    """Paired runs from the same start: median cond(Y) of ours / random (paper Table IV) <= 0.8 on
    the default quickstart (planner.cumulative_excitation; the paper's per-plan cost gives 0.99 to
    1.17 here: docs/identification.md)."""
    runs = {
        m: [run_online(quickstart, None, method=m, seed=seed, write=False) for seed in range(20)]
        for m in ("ours", "random")
    }
    cond = {m: np.array([s["cond_Y"] for s in r]) for m, r in runs.items()}
    mass_width = {
        m: np.array([s["estimate"]["upper"][0] - s["estimate"]["lower"][0] for s in r]) for m, r in runs.items()
    }
    ratio = np.median(cond["ours"]) / np.median(cond["random"])
    print(
        f"median cond(Y) ours {np.median(cond['ours']):.1f} / random {np.median(cond['random']):.1f} = {ratio:.2f} "
        f"(ours lower in {int(np.sum(cond['ours'] < cond['random']))}/20); median mass-interval width "
        f"ours {np.median(mass_width['ours']):.3f} kg, random {np.median(mass_width['random']):.3f} kg"
    )
    assert ratio <= 0.8


def test_wrong_model_leaves_the_tracking_bound(quickstart):
    """The certified bound is not vacuous: without the payload in the model it is exceeded (the
    paper's "wrong" has no identification phase: here it holds the 8 lb dumbbell at q0 for 2 s)."""
    from safesysid.online import build_online

    scene = load_scenario(SCENARIOS_DIR / "quickstart.yaml")
    scene.payload.dumbbell = "8lb"
    built = build_online(scene, "wrong")
    ctx = simulate_online(built, scene, 2.0)
    q = built.loggers["state"].FindLog(ctx).data()[: built.arm.n]
    q_d = built.loggers["desired"].FindLog(ctx).data()[: built.arm.n]
    ratio = np.max(np.abs(q_d - q) / np.asarray(built.tracking.position)[:, None])
    theta0, box = built.theta_prior
    truth = built.arm.true_theta()
    assert ratio > 1.0 and not np.all((box.lo <= truth) & (truth <= box.hi))


def test_a_command_beyond_the_torque_limit_is_a_failure(quickstart, monkeypatch):
    """The referee reads the controller's command BEFORE the actuator saturation: a controller
    that commands 1.2x the limit on joint 7 for 20 ms fails on torque_limit, although the torque
    that reaches the joint (saturated) never exceeds the limit."""
    from safesysid.systems.controller import systems as controller_systems

    make = controller_systems.make_controller

    def overdriven(kind, robot, gains, time_step):
        ctrl = make(kind, robot, gains, time_step=time_step)
        law = ctrl._torque
        spike = np.zeros(robot.n)
        spike[-1] = 1.2 * robot.joint_params.torque_limit[-1]

        def torque(context, *args):
            u = law(context, *args)
            return u + spike if 1.0 <= context.get_time() < 1.02 else u

        ctrl._torque = torque
        return ctrl

    monkeypatch.setattr(controller_systems, "make_controller", overdriven)
    scene = load_scenario(SCENARIOS_DIR / "quickstart.yaml")
    scene.planner.num_plans = 1  # one plan, 3 s: enough to see the spike
    summary = run_online(scene, None, method="ours", write=False)
    print({k: summary.get(k) for k in ("failure", "max_torque_ratio", "max_commanded_torque_ratio")})
    assert summary["max_torque_ratio"] <= 1.0 + 1e-9  # the saturated torque hides it ...
    assert summary["max_commanded_torque_ratio"] > 1.1  # ... the command does not
    assert summary["failure"] == "torque_limit" and not summary["success"]


def test_continuation_keeps_identification_going():
    """planner.continuation: refinement adopts a point only if the state its plan reaches at the next
    call has a certified plan that holds still there. identify_all with 1 s plans every 0.5 s, seed 1,
    5 lb: without it the first, most exciting plan leaves the arm where the next call certifies
    nothing (joint 6's torque bound) and it brakes; with it every call is certified, safe."""
    plans = "planner: {duration_s: 1.0, replan_period_s: 0.5, num_plans: 4, continuation: %s}"
    out = {}
    for on in ("false", "true"):
        scene = load_scenario(SCENARIOS_DIR / "identify_all.yaml", overrides=[plans % on, "payload: {dumbbell: 5lb}"])
        out[on] = run_online(scene, None, method="ours", seed=1, write=False)
    assert out["false"]["planner"]["status"][-1] == "infeasible_start" and out["false"]["planner"]["brakes"] == 1
    assert all(s in ("solved", "best_feasible") for s in out["true"]["planner"]["status"])
    assert out["true"]["planner"]["brakes"] == 0 and len(out["true"]["planner"]["status"]) == 4
    assert_safe(out["true"])
    assert out["true"]["contains_truth"] and out["true"]["estimate"]["consistent"]
