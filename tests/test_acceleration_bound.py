"""The joint-acceleration bound derived online from the dynamics under the held torque
(estimation/acceleration_bound.py): it holds the model's true q̈ along a simulated held-torque motion
(and certifies the quadrature there), is tight on one joint with the armature at its box's lower
end, and samples or a known motion faster than it are flagged. Printed with -s."""

import numpy as np
import pytest
from helpers import CENTRE, PRIOR, PRIOR_NOMINAL
from safesysid.systems import estimation as E
from safesysid.systems.estimation import acceleration_bound as ab
from safesysid.systems.model.payload import payload_theta_in_end_effector
from safesysid.systems.model.uncertainty import parameter_radius

H = 1e-3
NOISE = E.EstimatorSettings().declared_noise


def true_theta(robot, dumbbells):
    theta = robot.theta.copy()
    theta[robot.ee_slice] = robot.theta_e + payload_theta_in_end_effector(dumbbells["8lb"], robot.extra["grasp_point"])
    return theta


def box(robot, *, ee=PRIOR):
    """(centre, radius): θ_r ± 5 % (the estimator's floors) and the end effector's Table II prior."""
    centre, radius = robot.theta.copy(), parameter_radius(robot, 0.05, 0.05)
    centre[robot.ee_slice], radius[robot.ee_slice] = 0.5 * (ee[0] + ee[1]), 0.5 * (ee[1] - ee[0])
    return centre, radius


def acceleration(robot, q, v, u, theta):
    """The model's q̈ = M⁻¹(u − h(q, q̇)) at one state, M (armature included; equal to Drake's
    CalcMassMatrix of the plant: test_real_arm.py) from the standard regressor at unit q̈, in one call."""
    n = robot.n
    qs, vs = np.repeat(q[None], n + 2, 0), np.zeros((n + 2, n))
    vs[-1] = v
    acc = np.vstack([np.zeros(n), np.eye(n), np.zeros(n)])
    tau = robot.standard_regressor(qs, vs, acc) @ theta
    return np.linalg.solve((tau[1:-1] - tau[0]).T, u - tau[-1])


@pytest.fixture(scope="module")
def held(robot, dumbbells):
    """0.3 s of the model's own dynamics under a zero-order-hold torque (a Fourier motion's torque
    plus a random ±3 N·m per step), RK4 on 2 sub-steps per step: samples, torque, and per step the
    largest |q̈| at its sub-step states (both ends included)."""
    rng = np.random.default_rng(3)
    theta = true_theta(robot, dumbbells)
    t, motion = E.fourier_motion(rng, robot, 0.3, 1 / H, centre=CENTRE)
    q, v, a = motion(t)
    tau = robot.inverse_dynamics(q, v, a, theta=theta) + rng.uniform(-3, 3, q.shape)
    qs, vs, peak = [q[0]], [v[0]], []
    x, sub = np.concatenate([q[0], v[0]]), H / 2
    n = robot.n
    for k in range(len(t) - 1):
        f = lambda y: np.concatenate([y[n:], acceleration(robot, y[:n], y[n:], tau[k], theta)])  # noqa: B023, E731
        acc = []
        for _ in range(2):
            k1 = f(x)
            acc.append(k1[n:])
            k2 = f(x + 0.5 * sub * k1)
            k3 = f(x + 0.5 * sub * k2)
            x = x + sub / 6 * (k1 + 2 * k2 + 2 * k3 + f(x + sub * k3))
        acc.append(f(x)[n:])
        peak.append(np.abs(acc).max(0))
        qs.append(x[:n])
        vs.append(x[n:])
    return t, np.array(qs), np.array(vs), tau, np.array(peak), theta


def test_the_bound_holds_the_model_acceleration_along_a_held_torque_motion(robot, held):
    t, q, v, tau, peak, theta = held
    bound = ab.derived_acceleration_bound(robot, (t, q, v, tau), NOISE.bound_from_measured(tau), box(robot))
    ratio = bound / peak
    print(f"\nheld torque: bound / true peak |q̈| per step: min {ratio.min():.2f}, median {np.median(ratio):.2f}")
    assert np.all(np.isfinite(bound)) and np.all(peak <= bound)
    settings = E.EstimatorSettings(set_membership="none", derive_acceleration_bound=True)
    est = E.IncrementalEstimator(robot, settings=settings, prior=PRIOR, prior_nominal=PRIOR_NOMINAL)
    est.add(t, q, v, tau)
    r = est.rows
    residual = np.abs(r.Y @ theta[robot.ee_slice] + r.D_r @ theta[robot.rest_mask()] - r.T)
    print(f"rows: the true error at most {np.max(residual / r.quad):.3f} of the quadrature term")
    assert r.a5_certified.all() and not r.accel_violated.any() and np.all(residual <= r.quad)


def test_the_bound_is_tight_on_one_joint_with_the_armature_at_its_lower_end(robot, dumbbells):
    """Only the last joint moves, under its friction alone (u = h without that joint's friction):
    with θ exact but the armatures (truth at their lower end) and an exact torque, the bound on that
    joint is within 2 % above the model's |q̈| — an upper armature, or h without friction, breaks it."""
    n, theta = robot.n, true_theta(robot, dumbbells)
    ia = 10 * n + 4 * np.arange(n) + 2
    radius = np.zeros_like(theta)
    radius[ia] = 0.05 * theta[ia]
    centre = theta.copy()
    theta[ia] -= radius[ia]
    q, v = np.array(CENTRE, float), np.zeros(n)
    v[-1] = 0.5
    u = robot.standard_regressor(q[None], v[None], np.zeros((1, n)))[0] @ theta
    u[-1] -= robot.theta[10 * n + 4 * (n - 1) + 1] * v[-1] + robot.theta[10 * n + 4 * (n - 1)] * np.tanh(v[-1] / 0.01)
    true = np.abs(acceleration(robot, q, v, u, theta))
    t = np.array([0.0, H])
    bound = ab.derived_acceleration_bound(
        robot, (t, np.stack([q, q]), np.stack([v, v]), np.stack([u, u])), 0.0, (centre, radius)
    )[0]
    print(f"\none joint: bound / true |q̈_7| = {bound[-1] / true[-1]:.4f}")
    assert np.all(true <= bound) and bound[-1] <= 1.02 * true[-1]


def test_from_residual_bounds_every_mass_matrix_above_the_armature(robot):
    """|M⁻¹ r| ≤ the bound for M = the rigid mass matrix at random configurations + diag(Ia) and
    |r| ≤ ρ (its corners); equality for M = diag(Ia), r on one joint."""
    rng = np.random.default_rng(1)
    n, theta = robot.n, robot.theta.copy()
    ia = theta[10 * n + 4 * np.arange(n) + 2]
    rho = rng.uniform(0, 5, n)
    bound = ab.from_residual(rho, ia)
    for _ in range(20):
        m = robot.mass_matrix(rng.uniform(-2, 2, (1, n)), theta)[0]
        r = rho * rng.choice([-1.0, 1.0], n)
        assert np.all(np.abs(np.linalg.solve(m, r)) <= bound)
    one = np.zeros(n)
    one[2] = rho[2]
    assert np.isclose(ab.from_residual(one, ia)[2], rho[2] / ia[2], rtol=1e-11)


def test_samples_faster_than_the_dynamics_allow_latch_consistent_off(robot, held):
    """The held-torque log with q̇ raised by 0.05 rad/s from 0.2 s on (50 rad/s² on one step,
    which the held torque cannot produce): flagged, consistent latched off."""
    t, q, v, tau, _, _ = held
    v = v + 0.05 * (t[:, None] >= 0.2)
    settings = E.EstimatorSettings(set_membership="none", derive_acceleration_bound=True)
    est = E.IncrementalEstimator(robot, settings=settings, prior=PRIOR, prior_nominal=PRIOR_NOMINAL)
    est.add(t, q, v, tau)
    assert est.rows.accel_violated.sum() == 1
    assert est.update().problems and not est.consistent


def test_a_known_motion_faster_than_the_derived_bound_is_flagged(robot, dumbbells):
    """A Fourier motion with a velocity 0.05·sin(2πt/h) between the samples (314 rad/s², the samples
    unchanged) and its mean torque held: given the motion, the steps exceed the derived bound and
    consistent latches off; without it the samples cannot tell (the premise excludes such a motion)."""
    from test_quadrature_certificate import held_torque, wobbling

    theta = true_theta(robot, dumbbells)
    t, smooth = E.fourier_motion(np.random.default_rng(5), robot, 0.3, 1 / H, centre=CENTRE)
    moved = wobbling(smooth, 0.05)
    q, v, _ = moved(t)
    tau = held_torque(robot, moved, t, theta)
    settings = E.EstimatorSettings(set_membership="none", derive_acceleration_bound=True)
    flagged = {}
    for known in (True, False):
        est = E.IncrementalEstimator(robot, settings=settings, prior=PRIOR, prior_nominal=PRIOR_NOMINAL)
        est.add(t, q, v, tau, reference=moved if known else None)
        flagged[known] = bool(est.rows.accel_violated.any())
    assert flagged == {True: True, False: False}


def test_a_derived_bound_needs_a_held_torque_and_no_declared_one(robot):
    for extra in ({"torque_signal": "continuous"}, {"acceleration_bound_rad_s2": 1.0}):
        with pytest.raises(E.EstimatorError, match="derive_acceleration_bound"):
            E.IncrementalEstimator(robot, settings=E.EstimatorSettings(derive_acceleration_bound=True, **extra))


def test_a_step_without_a_bound_certifies_nothing(robot, held):
    """A bound of inf (what the derivation gives a step where no candidate passed): the rows keep
    A5's own term and say nothing is certified, and nothing is flagged."""
    t, q, v, tau, _, _ = held
    rows = {}
    for bound in (None, np.inf):
        est = E.IncrementalEstimator(robot, settings=E.EstimatorSettings(set_membership="none"), prior=PRIOR)
        est.add(t, q, v, tau, acceleration_bound=bound)
        rows[bound] = est.rows
    assert not rows[np.inf].a5_certified.any() and not rows[np.inf].accel_violated.any()
    assert np.array_equal(rows[np.inf].quad, rows[None].quad)


def test_a_closed_loop_run_with_the_derived_bound_is_certified_without_false_alarm(tmp_path):
    """The quickstart's first plan (3 s) on the simulated arm (Drake's plant, noisy torque sensor)
    with estimator.derive_acceleration_bound: no step's samples contradict the derived bound,
    summary.json says certified, consistent, the truth inside."""
    import json

    from safesysid.cli import main
    from safesysid.scenario import SCENARIOS_DIR

    text = "planner: {num_plans: 1}\nestimator: {derive_acceleration_bound: true}"
    assert main(["run", str(SCENARIOS_DIR / "quickstart.yaml"), "--out", str(tmp_path), "--scenario-text", text]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["estimate"]["quadrature_assumption"] == "certified"
    assert summary["estimate"]["consistent"] and summary["contains_truth"]
