"""Task trajectory (systems/task/trajectory.py): the math, the optimizer on the paper's three
experiment scenarios (verified independently on the link shapes and Drake's inverse dynamics),
the cache and the failure statuses."""

import dataclasses as dc

import numpy as np
import pytest
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.systems.config import ScenarioError
from safesysid.systems.controller.armour import TrackingBounds
from safesysid.systems.math.piecewise_bezier import Parametrization, PiecewiseBezier, jerk_gram
from safesysid.systems.model.uncertainty import parameter_box
from safesysid.systems.planner import reachability as reach
from safesysid.systems.task import cache as task_cache
from safesysid.systems.task import check as task_check
from safesysid.systems.task import trajectory as tt
from safesysid.systems.task.constraints import GRIPPER_TILT_TOL_RAD, TaskConstraints

EXPERIMENTS = ("experiment_a", "experiment_b", "experiment_c")


def problem_of(name, **settings):
    prob = tt.task_problem_from_scenario(load_scenario(SCENARIOS_DIR / f"{name}.yaml"))
    if settings:
        prob.settings = dc.replace(prob.settings, **settings)
    return prob


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    """{experiment: (problem, result)} through a fresh cache (each solved once per session)."""
    cache = tmp_path_factory.mktemp("task_cache")
    out = {}
    for name in EXPERIMENTS:
        prob = problem_of(name)
        out[name] = (prob, task_cache.task_trajectory_cached(prob, cache))
    return out


# ---- the curve and the cost --------------------------------------------------------------------
def test_pieces_start_and_end_at_rest_and_are_c2_at_the_junctions():
    rng = np.random.default_rng(1)
    for pieces in (2, 3):
        par = Parametrization.make(pieces)
        q_s, q_g = rng.normal(size=(2, 7))
        x = par.control_points(rng.normal(size=(par.r, 7)), q_s, q_g)
        traj = PiecewiseBezier(x.reshape(pieces, 6, 7), 0.7)
        start, end = traj.evaluate([0.0]), traj.evaluate([traj.duration])
        assert np.allclose(start[0], q_s) and np.allclose(end[0], q_g)
        assert max(np.abs(d).max() for d in start[1:3] + end[1:3]) < 1e-9
        for k in range(1, pieces):
            t = k * 0.7
            left, right = traj.evaluate([t - 1e-9]), traj.evaluate([t + 1e-9])
            jumps = [np.abs(a - b).max() / max(1.0, np.abs(a).max()) for a, b in zip(left, right)]
            assert max(jumps[:3]) < 1e-6, jumps  # q, dq, ddq continuous
            assert jumps[3] > 1e-3  # jerk is free to jump: the test sees a junction


def test_jerk_cost_is_the_integral_of_squared_jerk():
    rng = np.random.default_rng(2)
    par = Parametrization.make(2)
    x = par.control_points(rng.normal(size=(par.r, 7)), rng.normal(size=7), rng.normal(size=7))
    traj = PiecewiseBezier(x.reshape(2, 6, 7), 1.0)
    exact = np.einsum("ij,ik,kj->", x, jerk_gram(2, 1.0), x)
    total = 0.0
    for a in (0.0, 1.0):  # jerk jumps at the junction: integrate each piece on its own
        t = np.linspace(a, a + 1.0 - 1e-12, 40001)
        total += np.trapezoid((traj.evaluate(t)[3] ** 2).sum(1), t)
    assert abs(total - exact) < 1e-6 * exact


def test_constraint_jacobians_match_finite_differences():
    prob = problem_of("experiment_a")
    con = TaskConstraints(prob)
    q_goal, _ = tt.solve_placement_ik(prob)
    y = con.initial_guess(q_goal)
    spread = con.spread(y)
    d = np.random.default_rng(3).normal(size=y.shape) * 1e-6
    for name, fn in (("collision", lambda x: con.collision_grouped(x, spread)), ("torque", con.torque)):
        v0, jac = fn(y)
        v1, _ = fn(y + d)
        assert np.abs((v1 - v0).ravel() - jac @ d).max() < 1e-3 * np.abs(jac @ d).max(), name
    v0, jac = con.placement(q_goal)
    v1, _ = con.placement(q_goal + d[-7:])
    assert np.abs(v1 - v0 - jac @ d[-7:]).max() < 1e-3 * np.abs(jac @ d[-7:]).max()


# ---- the three experiments -------------------------------------------------------------------
@pytest.mark.parametrize("name", EXPERIMENTS)
def test_experiment_task_trajectory_is_found_and_verified_independently(solved, name):
    prob, res = solved[name]
    assert res.ok and res.status == "solved" and res.max_violation <= tt.FEASIBILITY_TOL, res.reason
    check = task_check.verify_task_trajectory(prob, res.trajectory)
    print(
        f"{name}: cost {res.cost:.1f}, sphere clearance {res.min_sphere_clearance_m:.4f} m, link-shape clearance "
        f"{check.min_clearance_m:.4f} m ({check.closest_pair}), torque {check.max_torque_ratio:.3f}, "
        f"velocity {check.max_velocity_ratio:.3f}, solve {res.solve_time_s:.2f} s"
    )
    assert check.ok, check.failures
    assert check.min_clearance_m > 0.005  # the spheres and the tube margin keep the link shapes away
    jp = prob.robot.joint_params
    # Velocity: limit minus the tube's velocity bound (hull: continuous time).
    t = np.linspace(0, res.trajectory.duration, 2001)
    _, v = res.trajectory.evaluate(t, orders=1)
    assert np.all(np.abs(v) <= jp.velocity_limit - prob.tracking.velocity + 1e-9)
    # Torque: the margin is claimed at the optimizer's samples; densely (Drake) it stays close.
    assert res.max_torque_ratio <= 1 - prob.settings.torque_margin_ratio + 1e-9
    assert check.max_torque_ratio <= 1 - prob.settings.torque_margin_ratio + 0.02
    # The ARMOUR certificate (tube + robust term, every instant) covers it with the payload known
    # exactly (rest of the robot +-5 %): the margin left for the tube is enough.
    ee = prob.theta[prob.robot.ee_slice]
    theta0, box = parameter_box(prob.robot, ee, ee, ee, rest_ratio=0.05, friction_ratio=0.05)
    certified, _ = task_check.certified_torque_ratio(prob, res.trajectory, theta0, box.lo, box.hi)
    assert check.max_torque_ratio <= certified <= 1.0, certified
    if prob.place_xyz is not None:
        assert check.placement_error_m < load_scenario(SCENARIOS_DIR / f"{name}.yaml").task.placement_tolerance_m
        assert check.gripper_tilt_rad <= GRIPPER_TILT_TOL_RAD
    else:
        assert np.allclose(res.q_goal, prob.goal_q)


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_the_obstacle_is_in_the_way(solved, name):
    """The straight joint-space minimum-jerk move to the same goal hits an obstacle (the
    verifier sees it), so the scenario's obstacle shapes the trajectory."""
    prob, res = solved[name]
    con = TaskConstraints(prob)
    q_goal = res.details.get("q_goal_ik_rad", res.q_goal)
    naive = task_check.verify_task_trajectory(prob, con.trajectory(con.initial_guess(np.asarray(q_goal))), rate_hz=250)
    assert not naive.ok and naive.min_clearance_m < 0, naive
    assert "obstacle" in " ".join(naive.closest_pair)


def test_drake_inverse_dynamics_of_the_verifier_agrees_with_the_regressor_model(solved):
    prob, res = solved["experiment_c"]
    con = TaskConstraints(prob)
    t = con.t_tau
    q, v, a = res.trajectory.evaluate(t, orders=2)
    mine = prob.robot.inverse_dynamics(q, v, a, theta=prob.theta)
    check = task_check.verify_task_trajectory(prob, res.trajectory, rate_hz=(len(t) - 1) / res.trajectory.duration)
    assert check.num_samples == len(t)
    assert abs(check.max_torque_ratio - np.max(np.abs(mine) / prob.robot.joint_params.torque_limit)) < 1e-9


def test_window_margin_covers_the_motion_between_collision_samples(monkeypatch):
    """Few samples (windows of 0.1 s), no tube: the spheres must clear every obstacle at EVERY
    instant, not only at the samples. Removing the window margin (spread = 0) breaks it: the
    same solve then dips into the post between samples (measured: -4.8 mm; the test can fail)."""

    def dense_sphere_clearance(prob, res):
        t = np.linspace(0, res.trajectory.duration, 4001)
        c, _ = reach.sphere_centres(
            prob.robot.tree, prob.spheres, res.trajectory.evaluate(t, 0)[0], with_jacobian=False
        )
        worst = np.inf
        for o in range(len(prob.boxes)):
            flat = c.reshape(-1, 3)
            sd, _ = reach.box_signed_distance(
                flat,
                np.broadcast_to(prob.boxes.centre[o], flat.shape),
                np.broadcast_to(prob.boxes.rotation[o], (len(flat), 3, 3)),
                np.broadcast_to(prob.boxes.half_size[o], flat.shape),
            )
            worst = min(worst, float(np.min(sd.reshape(c.shape[:2]) - prob.spheres.radius)))
        return worst

    prob = problem_of("experiment_b", collision_samples=20)
    prob.tracking = TrackingBounds.zero(prob.robot.n)
    res = tt.solve_task_trajectory(prob, fallback=False)
    assert res.ok, res.reason
    assert res.min_sphere_clearance_m < 1e-3  # a constraint is active: the test sits on the boundary
    assert dense_sphere_clearance(prob, res) >= 0
    monkeypatch.setattr(TaskConstraints, "spread", lambda self, y: np.zeros((len(self.t_col), len(self.p.spheres))))
    broken = tt.solve_task_trajectory(prob, fallback=False)
    assert broken.ok
    assert dense_sphere_clearance(prob, broken) < -1e-3


def test_torque_rows_are_added_when_the_torque_limit_binds():
    """Experiment (c) reaches 0.57 of a torque limit unconstrained; allow 0.5: the rows are
    added after the first round and the Drake check at 1 kHz stays at the allowed ratio."""
    prob = problem_of("experiment_c", torque_margin_ratio=0.5)
    res = tt.solve_task_trajectory(prob, fallback=False)
    assert res.ok, res.reason
    assert res.details["attempts"][0]["rounds"] >= 2
    assert res.max_torque_ratio <= 0.5 + 1e-9
    check = task_check.verify_task_trajectory(prob, res.trajectory)
    assert check.ok and check.max_torque_ratio <= 0.5 + 0.01, check.max_torque_ratio


# ---- cache ---------------------------------------------------------------------------------------
def small_problem(**changes):
    """Free space (no obstacles), joint goal, few samples: a solve in well under a second."""
    prob = problem_of("experiment_c", collision_samples=20, torque_samples=11)
    prob.obstacles, prob.goal_q = [], np.array([0.5, 0.4, 0.0, 1.9, 0.0, 0.9, 1.57])
    for key, value in changes.items():
        setattr(prob, key, value)
    prob.__post_init__()
    return prob


def test_cache_loads_without_solving_and_any_input_change_recomputes(tmp_path, monkeypatch):
    first = task_cache.task_trajectory_cached(small_problem(), tmp_path)
    assert first.ok and first.details["cache"] == "miss"
    calls = []
    real_solve = tt.solve_task_trajectory
    monkeypatch.setattr(tt, "solve_task_trajectory", lambda *a, **k: calls.append(1) or real_solve(*a, **k))
    again = task_cache.task_trajectory_cached(small_problem(), tmp_path)
    assert again.details["cache"] == "hit" and not calls
    assert np.array_equal(again.trajectory.control_points, first.trajectory.control_points)
    assert again.cost == first.cost and np.array_equal(again.q_goal, first.q_goal)
    base = task_cache.cache_key(small_problem())
    obstacle = load_scenario(SCENARIOS_DIR / "experiment_c.yaml").obstacles[0]
    variants = {
        "q_start": dict(q_start=small_problem().q_start + 1e-9),
        "goal": dict(goal_q=small_problem().goal_q + [0.01, 0, 0, 0, 0, 0, 0]),
        "obstacles": dict(obstacles=[obstacle]),
        "floor": dict(floor_z=-0.01),
        "payload": dict(theta=small_problem().theta * 1.001),
        "tube": dict(tracking=TrackingBounds.zero(7)),
        "settings": dict(settings=dc.replace(small_problem().settings, torque_margin_ratio=0.3)),
    }
    keys = {name: task_cache.cache_key(small_problem(**change)) for name, change in variants.items()}
    keys["solver"] = task_cache.cache_key(small_problem(), solver="ipopt")
    assert all(k != base for k in keys.values()) and len(set(keys.values())) == len(keys)
    changed = task_cache.task_trajectory_cached(small_problem(**variants["goal"]), tmp_path)
    assert changed.details["cache"] == "miss" and len(calls) == 1
    assert np.allclose(changed.q_goal, variants["goal"]["goal_q"])


def test_cache_key_hashes_the_model_files(tmp_path):
    """A sphere file with the same numbers but one more comment is another input."""
    from helpers import params_with_spheres
    from safesysid.systems.model.robot_model import MODELS_DIR, load_robot

    spheres = tmp_path / "spheres.yaml"
    spheres.write_text((MODELS_DIR / "kinova_gen3_spheres.yaml").read_text() + "# edited\n")
    prob = small_problem()
    other = small_problem(
        robot=load_robot(
            params_path=params_with_spheres(tmp_path, spheres), coulomb_smoothing=prob.robot.coulomb_smoothing
        )
    )
    assert task_cache.cache_key(other) != task_cache.cache_key(prob)


# ---- failures are statuses, not crashes ---------------------------------------------------------
def test_unreachable_placement_is_a_clear_failure():
    prob = problem_of("experiment_a")
    prob.place_xyz = np.array([1.6, 0.0, 0.2])  # beyond the arm's reach
    res = tt.solve_task_trajectory(prob)
    assert not res.ok and res.status == "goal_unreachable" and res.trajectory is None
    assert "1.6" in res.reason


def test_blocked_goal_and_blocked_start_are_clear_failures():
    prob = problem_of("experiment_c")
    ob = prob.obstacles[0]
    # A box around where the payload is at the goal configuration.
    c, _ = reach.sphere_centres(prob.robot.tree, prob.spheres, prob.goal_q[None], with_jacobian=False)
    box = dc.replace(ob, name="box_on_goal", xyz_m=list(c[0, -1]), size_m=[0.05, 0.05, 0.05])
    blocked = small_problem(obstacles=[box], goal_q=prob.goal_q)
    res = tt.solve_task_trajectory(blocked)
    assert not res.ok and res.status == "goal_blocked" and "box_on_goal" in res.reason
    start = small_problem(q_start=prob.goal_q, goal_q=prob.q_start, obstacles=[box])
    res = tt.solve_task_trajectory(start)
    assert not res.ok and res.status == "start_blocked" and "box_on_goal" in res.reason


def test_solver_giving_up_is_reported_not_raised():
    prob = problem_of("experiment_a", max_iterations=1)
    res = tt.solve_task_trajectory(prob)
    assert not res.ok and res.status == "infeasible" and res.trajectory is None
    assert "snopt" in res.reason and "ipopt" in res.reason


# ---- scenario section (bad task fields: tests/test_scenario.py) -----------------------------------
def test_scenario_without_task_has_no_task_phase():
    from safesysid.systems.config import task_enabled

    s = load_scenario(SCENARIOS_DIR / "quickstart.yaml")
    assert not task_enabled(s)
    with pytest.raises(ScenarioError, match="task"):
        tt.task_problem_from_scenario(s)
    assert all(task_enabled(load_scenario(SCENARIOS_DIR / f"{n}.yaml")) for n in EXPERIMENTS)
