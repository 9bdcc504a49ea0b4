"""Closed loop (real arm + ARMOUR + degree-5 Bezier source): the tracking error stays inside the
certified ultimate bound at every step when [theta] contains the truth, and leaves it with the
"wrong" model (so the bound is not vacuous). Baselines run behind the same ports.

Sample size: n_trials(1, 20) random trajectories per payload (SAFESYSID_FULL=1 for 20).
"""
import numpy as np
import pytest

from safesysid.scenario import load_scenario, robot_from_scenario
from safesysid.systems import controller as C
from safesysid.systems.bezier import QuinticBezier
from safesysid.systems.controllers import build_closed_loop, simulate_closed_loop
from safesysid.systems.intervals import Interval
from safesysid.systems.real_arm import scenario_dumbbell, true_theta

from conftest import n_trials

PAYLOADS = ["none", "4lb", "5lb", "6lb", "7lb", "8lb"]


@pytest.fixture(scope="module")
def robot():
    return robot_from_scenario(load_scenario())


def random_trajectory(s, rng):
    q0 = np.array(s.q0_rad) + rng.uniform(-0.2, 0.2, 7)
    q_end = q0 + np.array(s.planner.k_range_rad) * rng.uniform(-1, 1, 7)
    return q0, (QuinticBezier(q0, np.zeros(7), np.zeros(7), s.planner.duration_s), q_end)


def run(s, robot, theta0, box, q0, trajectory, kind="armour", duration=None, theta_true=None):
    """Simulate; returns per-step ratios |e_i| / (eps/Kr_i), |r| / eps, |u_i| / limit_i (and the
    true Lyapunov value 1/2 r^T M(q; theta_true) r / V_max when theta_true is given)."""
    loop = build_closed_loop(s, trajectory, theta0, box, kind=kind, robot=robot)
    logs = simulate_closed_loop(loop, q0, duration or s.planner.duration_s)
    x, d, u = logs["state"][1], logs["desired"][1], logs["torque"][1]
    n = robot.n
    gains = loop.controller.gains.armour
    e = C.wrap_error(d[:, :n] - x[:, :n], robot.joint_params.continuous)
    r = (d[:, n:2 * n] - x[:, n:]) + gains.Kr * e
    bounds = C.tracking_bounds_for(robot, gains, box.lo)
    lyapunov = np.zeros(1)
    if theta_true is not None:
        m_true = robot.mass_matrix(x[:, :n], theta_true)
        lyapunov = 0.5 * np.einsum("ki,kij,kj->k", r, m_true, r) / gains.V_max
    return {"position": np.abs(e) / bounds.position, "r": np.linalg.norm(r, axis=1) / bounds.eps, "lyapunov": lyapunov,
            "velocity": np.abs(d[:, n:2 * n] - x[:, n:]) / bounds.velocity,
            "torque": np.abs(u) / robot.joint_params.torque_limit, "error": np.abs(e), "bounds": bounds}


def interval_around_truth(robot, theta_true, rng):
    """theta0 random inside a box that contains the truth (end effector +-5..30 %, rest +-5 %)."""
    te = theta_true[robot.ee_slice]
    rad = rng.uniform(0.05, 0.3) * np.abs(te) + 0.01
    lo, hi = te - rad * rng.uniform(0.2, 1.0, 10), te + rad * rng.uniform(0.2, 1.0, 10)
    _, box = C.parameter_box(robot, te, lo, hi)
    theta0 = rng.uniform(box.lo, box.hi)
    assert np.all(box.contains(theta_true))
    return theta0, box


@pytest.mark.parametrize("bell", PAYLOADS)
def test_error_inside_ultimate_bound(robot, bell):
    s = load_scenario(overrides={"payload": {"dumbbell": bell}})
    theta_true = true_theta(robot, scenario_dumbbell(s))
    rng = np.random.default_rng(100 + PAYLOADS.index(bell))
    worst = {"position": 0.0, "r": 0.0, "velocity": 0.0, "lyapunov": 0.0, "torque": 0.0}
    for _ in range(n_trials(1, 20)):
        theta0, box = interval_around_truth(robot, theta_true, rng)
        q0, trajectory = random_trajectory(s, rng)
        out = run(s, robot, theta0, box, q0, trajectory, theta_true=theta_true)
        for key in worst:
            worst[key] = max(worst[key], float(out[key].max()))
    print(f"{bell}: max |e|/bound {worst['position']:.3f}, |r|/eps {worst['r']:.3f}, "
          f"V/V_max {worst['lyapunov']:.3f}, |u|/limit {worst['torque']:.3f}")
    assert worst["lyapunov"] <= 1.0  # the barrier itself: V(true) <= V_max at every step
    assert worst["position"] <= 1.0 and worst["r"] <= 1.0 and worst["velocity"] <= 1.0
    assert worst["torque"] <= 1.0


def test_conservative_interval_with_8lb_holds(robot):
    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}})
    ii = s.initial_interval
    theta0, box = C.parameter_box(robot, ii.nominal, ii.lower, ii.upper)
    assert np.all(box.contains(true_theta(robot, scenario_dumbbell(s))))
    rng = np.random.default_rng(8)
    for _ in range(n_trials(1, 20)):
        q0, trajectory = random_trajectory(s, rng)
        out = run(s, robot, theta0, box, q0, trajectory, theta_true=true_theta(robot, scenario_dumbbell(s)))
        print(f"conservative 8lb: max |e|/bound {out['position'].max():.3f}, |r|/eps {out['r'].max():.3f}, "
              f"V/V_max {out['lyapunov'].max():.3f}")
        assert out["position"].max() <= 1.0 and out["r"].max() <= 1.0 and out["torque"].max() <= 1.0
        assert out["lyapunov"].max() <= 1.0
        assert out["position"].max() > 0.05  # the payload is felt: the robust term is working


def test_wrong_model_leaves_the_bound(robot):
    """No payload in the model and a zero-width interval while the arm holds 8 lb: the bound
    is violated, so the containment above is a real property of a correct [theta]."""
    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}})
    theta0 = robot.theta.copy()
    box = Interval(theta0, theta0)
    assert not np.all(box.contains(true_theta(robot, scenario_dumbbell(s))))
    q0, trajectory = random_trajectory(s, np.random.default_rng(9))
    out = run(s, robot, theta0, box, q0, trajectory, theta_true=true_theta(robot, scenario_dumbbell(s)))
    print(f"wrong model 8lb: max |e|/bound {out['position'].max():.3f}, |r|/eps {out['r'].max():.3f}, "
          f"V/V_max {out['lyapunov'].max():.3f}")
    assert out["position"].max() > 1.0 and out["r"].max() > 1.0 and out["lyapunov"].max() > 1.0


@pytest.mark.parametrize("kind", ["pid", "adaptive", "adaptive_robust"])
def test_baselines_track(robot, kind):
    """The baselines run behind the same ports and follow the trajectory (loosely: no bound)."""
    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}})
    ii = s.initial_interval
    theta0, box = C.parameter_box(robot, ii.nominal, ii.lower, ii.upper)
    q0, trajectory = random_trajectory(s, np.random.default_rng(10))
    out = run(s, robot, theta0, box, q0, trajectory, kind=kind)
    print(f"{kind}: max |e| {out['error'].max():.4f} rad")
    assert np.all(np.isfinite(out["error"])) and out["error"].max() < 0.1
    assert out["torque"].max() <= 1.0


def test_adaptive_estimate_moves_toward_the_payload(robot):
    """adap-1's end-effector mass estimate, started at the model without payload, grows."""
    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}})
    ii = s.initial_interval
    theta0, box = C.parameter_box(robot, robot.theta_e, ii.lower, ii.upper)
    q0, trajectory = random_trajectory(s, np.random.default_rng(11))
    loop = build_closed_loop(s, trajectory, theta0, box, kind="adaptive", robot=robot, log=False)
    from pydrake.systems.analysis import Simulator

    sim = Simulator(loop.diagram)
    loop.arm.set_state(sim.get_mutable_context(), q0)
    sim.AdvanceTo(2.0)
    ctx = loop.controller.GetMyContextFromRoot(sim.get_context())
    mass_hat = loop.controller.estimate(ctx, theta0, box)[robot.ee_slice][0]
    m_true = true_theta(robot, scenario_dumbbell(s))[robot.ee_slice][0]
    assert abs(mass_hat - m_true) < abs(robot.theta_e[0] - m_true)


def test_trajectory_source_matches_bezier_and_switches_pieces():
    from safesysid.systems.trajectory_source import Piece, make_trajectory_source

    rng = np.random.default_rng(12)
    q0, v0, a0 = rng.normal(size=(3, 7))
    first = QuinticBezier(q0, v0, a0, 2.0)
    end1 = q0 + 0.1
    piece1 = Piece(0.0, first, end1)
    q1, v1, a1 = (x[0] for x in first.evaluate([1.0], end1))
    second = QuinticBezier(q1, v1, a1, 2.0)
    end2 = q1 - 0.2
    source = make_trajectory_source(7, [piece1])
    ctx = source.CreateDefaultContext()
    for t in (0.0, 0.4, 1.3, 2.0, 2.5):
        ctx.SetTime(t)
        expected = np.concatenate([x[0] for x in first.evaluate([t], end1)])
        np.testing.assert_allclose(source.get_output_port().Eval(ctx), expected, atol=1e-12)
    source.append_piece(ctx, Piece(1.0, second, end2))
    for t in (0.5, 1.0, 1.7, 3.5):
        ctx.SetTime(t)
        curve, start, end = (first, 0.0, end1) if t < 1.0 else (second, 1.0, end2)
        expected = np.concatenate([x[0] for x in curve.evaluate([t - start], end)])
        np.testing.assert_allclose(source.get_output_port().Eval(ctx), expected, atol=1e-12)
