"""ARMOUR law: regressors, hand-computed cases, containment and exactness of w_bar / V_bar,
the certified sigma_min and the per-joint tracking bounds."""

import numpy as np
import pytest
from helpers import mass_matrices
from safesysid.systems.controller import armour as C
from safesysid.systems.math.intervals import Interval
from safesysid.systems.model import uncertainty
from safesysid.systems.model.payload import load_dumbbells, payload_theta_in_end_effector
from safesysid.systems.model.robot_model import MODELS_DIR


@pytest.fixture(scope="module")
def dyn(robot):
    return C.ControllerDynamics(robot)


def _box(robot, rng, ee_ratio=0.2):
    theta_e = robot.theta_e + payload_theta_in_end_effector(
        load_dumbbells(MODELS_DIR / "dumbbells.yaml")["6lb"], robot.extra["grasp_point"]
    )
    rad = ee_ratio * np.abs(theta_e) + 1e-3
    return uncertainty.parameter_box(robot, theta_e + rng.uniform(-0.5, 0.5, 10) * rad, theta_e - rad, theta_e + rad)


def test_fast_regressors_equal_robot_model(robot, dyn):
    rng = np.random.default_rng(0)
    for _ in range(5):
        q, v, va, aa, x = rng.normal(size=(5, robot.n))
        wp, wm = dyn.regressors(q, v, va, aa=aa, x=x)
        np.testing.assert_allclose(wp, robot.passivity_regressor(q[None], v[None], va[None], aa[None])[0], atol=1e-11)
        np.testing.assert_allclose(wm, robot.momentum_regressor(q[None], x[None])[0], atol=1e-11)
    general = C.ControllerDynamics(robot)
    general.serial = False  # the tree path (loop over parents) gives the same
    np.testing.assert_allclose(general.regressors(q, v, va, aa=aa, x=x)[0], wp, atol=1e-12)


def test_passivity_form_is_christoffel(robot, dyn):
    """Mdot - 2C skew: x^T (Mdot - 2 C) x = 0, with C(q, v) x from Wp and Mdot by differences."""
    rng = np.random.default_rng(1)
    q, v, x = rng.normal(size=(3, robot.n))
    theta = robot.theta
    zero = np.zeros(robot.n)
    c_x = (dyn.regressors(q, v, x, aa=zero, x=zero)[0] - dyn.regressors(q, zero, zero, aa=zero, x=zero)[0]) @ theta
    c_x -= robot.joint_params.viscous * x + robot.joint_params.coulomb * np.tanh(x / 0.01)  # friction(va) columns
    d = 1e-6
    m_dot = (robot.mass_matrix(q + d * v, theta)[0] - robot.mass_matrix(q - d * v, theta)[0]) / (2 * d)
    assert abs(x @ m_dot @ x - 2 * x @ c_x) < 1e-6 * (1 + abs(x @ m_dot @ x))


def test_tracking_errors_hand_case(robot):
    cont = robot.joint_params.continuous
    kr = np.arange(1.0, 8.0)
    q = np.zeros(7)
    q_d = np.zeros(7)
    q_d[0], q[0] = np.pi - 0.1, -np.pi + 0.1  # continuous: wraps to -0.2
    q_d[1], q[1] = 0.3, 0.1  # limited joint: plain difference
    v = np.full(7, 0.5)
    qd_d = np.full(7, 0.25)
    qdd_d = np.full(7, 2.0)
    err = C.tracking_errors(kr, q, v, q_d=q_d, qd_d=qd_d, qdd_d=qdd_d, continuous=cont)
    assert err.e[0] == pytest.approx(-0.2) and err.e[1] == pytest.approx(0.2)
    np.testing.assert_allclose(err.edot, -0.25)
    np.testing.assert_allclose(err.qd_a, qd_d + kr * err.e)
    np.testing.assert_allclose(err.qdd_a, qdd_d - 0.25 * kr)
    np.testing.assert_allclose(err.r, -0.25 + kr * err.e)
    assert C.wrap_error(np.array([2 * np.pi - 0.2]), np.array([False]))[0] == pytest.approx(2 * np.pi - 0.2)


def test_robust_input_hand_cases():
    r = np.array([3.0, 4.0])
    w_bar = np.array([1.0, 2.0])
    v, lam = C.robust_input(r, w_bar, h=0.5, alpha=2.0)
    assert lam == pytest.approx(np.sqrt(5) - 0.2)
    np.testing.assert_allclose(v, lam * np.array([0.6, 0.8]))
    v, lam = C.robust_input(r, w_bar, h=100.0, alpha=2.0)  # deep inside the barrier: off
    assert lam == 0 and not v.any()
    v, lam = C.robust_input(r, w_bar, h=-1.0, alpha=2.0)  # outside: pushes back harder
    assert lam == pytest.approx(0.4 + np.sqrt(5))
    v, lam = C.robust_input(np.zeros(2), w_bar, h=-1.0, alpha=2.0)
    assert lam == 0 and not v.any()


def _quickstart_prior(robot):
    """theta0, [theta] of the quickstart (paper Table II end effector, the rest +-5 %) and the true theta."""
    from safesysid.scenario import load_scenario
    from safesysid.systems.plant.arm_plant import scenario_dumbbell, true_theta

    s = load_scenario(MODELS_DIR.parent / "scenarios" / "quickstart.yaml")
    ii = s.initial_interval
    theta0, box = uncertainty.parameter_box(robot, np.array(ii.nominal), np.array(ii.lower), np.array(ii.upper))
    return s, theta0, box, true_theta(robot, scenario_dumbbell(s))


def _on_boundary(robot, q, theta_true, direction, V_max):
    """r along `direction` with the TRUE 1/2 r^T M(q; theta_true) r = V_max."""
    m = mass_matrices(robot, q, theta_true)[0]
    return direction * np.sqrt(2 * V_max / (direction @ m @ direction))


def test_mass_spread_bounds_the_change_of_the_lyapunov_value(robot):
    """1/2 r^T (M(theta) - M(theta')) r <= 1/2 |r|^2 mu(q) for theta, theta' in the box (box vertices
    and the extreme pair for r), and mu is nearly attained."""
    _, _, box, _ = _quickstart_prior(robot)
    rng = np.random.default_rng(20)
    n = robot.n
    worst = 0.0
    for _ in range(30):
        q = rng.uniform(-np.pi, np.pi, n)
        mu = C.mass_spread(robot, q, box.lo, theta_hi=box.hi)
        rs = np.array([rng.normal(size=n) for _ in range(20)])
        rows = np.einsum("ri,rip->rp", rs, robot.momentum_regressor(np.repeat(q[None], 20, 0), rs))  # r^T dM/dθ_k r
        hi_theta, lo_theta = np.where(rows >= 0, box.hi, box.lo), np.where(rows >= 0, box.lo, box.hi)
        m_hi, m_lo = np.split(mass_matrices(robot, np.repeat(q[None], 40, 0), np.vstack([hi_theta, lo_theta])), 2)
        for r, dm in zip(rs, m_hi - m_lo):
            gap = 0.5 * r @ dm @ r
            assert gap <= 0.5 * (r @ r) * mu
            worst = max(worst, gap / (0.5 * (r @ r) * mu))
    print(f"max spread of 1/2 r^T M r over the box / (1/2 |r|^2 mu): {worst:.3f}")
    assert worst > 0.5


@pytest.mark.parametrize("V_max", [0.005, 0.02])
def test_robust_gain_on_the_tube_boundary(robot, dyn, V_max):
    """lambda <= |w_bar| + alpha eps mu(q) / 2 (robust_gain_bound) ON the tube boundary (true V =
    V_max), where h < 0 and lambda > |w_bar|: the quickstart prior (Table II), random
    configurations, theta_true in the box (a vertex half the time), random r directions (along one
    joint half the time, where |v_j| = lambda), random position errors up to the bound."""
    s, theta0, box, _ = _quickstart_prior(robot)
    gains = C.ArmourGains(np.array(s.controller.Kr, float), s.controller.alpha, V_max)
    bounds = C.tracking_bounds_for(robot, gains, box.lo)
    jp = robot.joint_params
    q_lo, q_hi = np.where(jp.continuous, -np.pi, jp.position_lower), np.where(jp.continuous, np.pi, jp.position_upper)
    rng = np.random.default_rng(21)
    n = robot.n
    over, ratio, negative = [], [], 0
    for _ in range(300):
        q_d = rng.uniform(q_lo, q_hi)
        theta_true = rng.uniform(box.lo, box.hi)
        if rng.uniform() < 0.5:
            theta_true = np.where(rng.uniform(size=theta_true.size) < 0.5, box.lo, box.hi)
        e = rng.uniform(-1, 1, n) * bounds.position / (1 + 1e-12)
        direction = rng.normal(size=n) if rng.uniform() < 0.5 else np.eye(n)[rng.integers(n)] * rng.choice([-1, 1])
        q = q_d - e
        r = _on_boundary(robot, q, theta_true, direction, V_max)
        qd_d, qdd_d = rng.uniform(-1, 1, (2, n))
        out = C.armour_control(dyn, gains, q, qd_d - (r - gains.Kr * e), q_d, qd_d, qdd_d, theta0, box)
        np.testing.assert_allclose(out.err.r, r, atol=1e-12)
        w_norm = np.linalg.norm(out.w_bar)
        bound = C.robust_gain_bound(
            w_norm, gains.alpha, bounds.eps, mu=C.mass_spread(robot, q, box.lo, theta_hi=box.hi)
        )
        assert out.lam <= bound and np.all(np.abs(out.v) <= bound)
        negative += out.h < 0
        over.append(out.lam - w_norm)
        ratio.append((out.lam - w_norm) / (bound - w_norm))
    print(
        f"V_max {V_max}: h < 0 in {negative}/300 boundary states; lambda - |w_bar| up to {max(over):.3f} N m "
        f"(the old bound |v_j| <= |w_bar| fails in {sum(o > 0 for o in over)}); "
        f"up to {max(ratio):.3f} of the certified excess alpha eps mu / 2"
    )
    assert negative > 150 and max(over) > 0.3  # the states the old bound got wrong are sampled
    assert max(ratio) > 0.2  # the certified excess is not absurdly loose


def test_reproduction_lambda_exceeds_w_bar_at_the_quickstart_pose(robot, dyn):
    """Issue 11: quickstart prior, q = q0, e = 0, r along joint 4 with the TRUE V = V_max: h < 0 and
    |v_4| = lambda > |w_bar| (the old planner bound), <= the certified bound."""
    s, theta0, box, theta_true = _quickstart_prior(robot)
    gains = C.ArmourGains(np.array(s.controller.Kr, float), s.controller.alpha, s.controller.V_max)
    q0 = np.array(s.q0_rad)
    r = _on_boundary(robot, q0, theta_true, np.eye(robot.n)[3], gains.V_max)
    out = C.armour_control(dyn, gains, q0, -r, q0, np.zeros(robot.n), np.zeros(robot.n), theta0, box)
    w_norm = np.linalg.norm(out.w_bar)
    eps = C.tracking_bounds_for(robot, gains, box.lo).eps
    bound = C.robust_gain_bound(w_norm, gains.alpha, eps, mu=C.mass_spread(robot, q0, box.lo, theta_hi=box.hi))
    print(
        f"h = {out.h:.5f} J, |v_4| = {abs(out.v[3]):.3f} N m, |w_bar| = {w_norm:.3f} N m, "
        f"certified bound {bound:.3f} N m"
    )
    assert out.h < 0 and abs(out.v[3]) > w_norm + 0.3
    assert abs(out.v[3]) <= bound


def test_law_on_the_trajectory_is_inverse_dynamics(robot, dyn):
    """e = edot = 0: r = 0, no robust input, u = M qdd + C qd + g + F of the nominal model."""
    rng = np.random.default_rng(2)
    theta0, box = _box(robot, rng)
    gains = C.ArmourGains(np.array([5.0] * 4 + [7.0] * 3), 20.0, 0.02)
    q, qd, qdd = rng.normal(size=(3, 7))
    out = C.armour_control(dyn, gains, q, qd, q, qd, qdd, theta0, box)
    assert out.lam == 0 and not out.v.any() and out.V_bar == 0 and out.h == pytest.approx(0.02)
    np.testing.assert_allclose(out.u, robot.inverse_dynamics(q[None], qd[None], qdd[None], theta=theta0)[0], atol=1e-10)


def test_law_hand_assembled(robot, dyn):
    """u = Wp theta0 + lambda r/|r| with every piece recomputed independently."""
    rng = np.random.default_rng(3)
    theta0, box = _box(robot, rng)
    gains = C.ArmourGains(np.array([5.0] * 4 + [7.0] * 3), 20.0, 0.02)
    q, v = rng.normal(size=(2, 7))
    q_d, qd_d, qdd_d = q + 0.03 * rng.normal(size=7), v + 0.1 * rng.normal(size=7), rng.normal(size=7)
    out = C.armour_control(dyn, gains, q, v, q_d, qd_d, qdd_d, theta0, box)
    e = C.wrap_error(q_d - q, robot.joint_params.continuous)
    r = (qd_d - v) + gains.Kr * e
    wp = robot.passivity_regressor(
        q[None], v[None], (qd_d + gains.Kr * e)[None], (qdd_d + gains.Kr * (qd_d - v))[None]
    )[0]
    tau_nom = wp @ theta0
    w_bar = np.maximum(
        wp @ box.mid + np.abs(wp) @ (box.hi - box.lo) / 2 - tau_nom,
        tau_nom - (wp @ box.mid - np.abs(wp) @ (box.hi - box.lo) / 2),
    )
    m = robot.momentum_regressor(q[None], r[None])[0]
    v_bar = 0.5 * (r @ m @ box.mid + np.abs(r @ m) @ (box.hi - box.lo) / 2)
    h = 0.02 - v_bar
    lam = max(0.0, -20.0 * h / np.linalg.norm(r) + np.linalg.norm(w_bar))
    np.testing.assert_allclose(out.tau_nom, tau_nom, atol=1e-10)
    np.testing.assert_allclose(out.w_bar, w_bar, rtol=1e-9, atol=1e-10)
    assert out.V_bar == pytest.approx(v_bar, rel=1e-9)
    assert out.lam == pytest.approx(lam, rel=1e-9, abs=1e-12)
    np.testing.assert_allclose(out.u, tau_nom + lam * r / np.linalg.norm(r), atol=1e-9)


def test_disturbance_and_lyapunov_bounds_contain_and_are_exact(robot, dyn):
    rng = np.random.default_rng(4)
    theta0, box = _box(robot, rng)
    for _ in range(5):
        q, v, va, aa, r = rng.normal(size=(5, 7))
        wp, wm = dyn.regressors(q, v, va, aa=aa, x=r)
        tau_nom, tau_box, w_bar = C.disturbance_bound(wp, theta0, box)
        v_bar = C.lyapunov_upper(wm, r, box)
        thetas = rng.uniform(box.lo, box.hi, (2000, box.lo.size))
        tau = thetas @ wp.T
        assert np.all(np.abs(tau - tau_nom) <= w_bar)
        m_all = mass_matrices(robot, np.broadcast_to(q, (50, q.size)), thetas[:50])
        assert max(0.5 * r @ m @ r for m in m_all) <= v_bar
        # Exact (not vacuous): the box vertex that maximises each expression attains the bound.
        for i in range(7):
            vertex = np.where(wp[i] >= 0, box.hi, box.lo)
            assert wp[i] @ vertex == pytest.approx(tau_box.hi[i], rel=1e-12, abs=1e-9)
        row = r @ wm
        vertex = np.where(row >= 0, box.hi, box.lo)
        assert 0.5 * r @ robot.mass_matrix(q[None], vertex)[0] @ r == pytest.approx(v_bar, rel=1e-9)


SIGMA_SAMPLES = 3000  # configurations (README "Tracking" quotes this number)


def test_sigma_min_certified_and_nearly_tight(robot):
    """Lower bound by the armature argument; sampled physical (q, theta) can only confirm it,
    and the smallest sampled eigenvalue is within a few % (the bound is not vacuous)."""
    rng = np.random.default_rng(5)
    n = robot.n
    bells = [None] + list(load_dumbbells(MODELS_DIR / "dumbbells.yaml").values())
    theta_lo = robot.theta * (1 - 0.05 * np.sign(robot.theta))
    sigma = C.mass_matrix_lower_bound(n, theta_lo)
    assert sigma == pytest.approx(0.95 * robot.joint_params.armature.min())
    ia = robot.joint_params.armature
    smallest = np.inf
    for k, bell in enumerate(bells):  # the payloads in turn, SIGMA_SAMPLES configurations in all
        count = SIGMA_SAMPLES // len(bells) + (k < SIGMA_SAMPLES % len(bells))
        theta = robot.theta.copy()
        if bell is not None:
            theta[robot.ee_slice] += payload_theta_in_end_effector(bell, robot.extra["grasp_point"])
        q = rng.uniform(-np.pi, np.pi, (count, n))
        m = robot.mass_matrix(q, theta)
        m[:, np.arange(n), np.arange(n)] += rng.uniform(0.95 * ia, ia, (count, n)) - ia  # Ia anywhere in its box
        smallest = min(smallest, np.linalg.eigvalsh(m)[:, 0].min())
    print(
        f"certified sigma_min {sigma:.4f} kg m^2; smallest eigenvalue in {SIGMA_SAMPLES} sampled configurations "
        f"{smallest:.4f}"
    )
    assert sigma <= smallest < 1.1 * sigma


def test_sigma_min_without_armature_is_zero_bound():
    assert C.mass_matrix_lower_bound(2, np.zeros(28)) == 0
    assert C.ultimate_bound(0.02, 0.0) == np.inf


def test_tracking_bounds_formulas_and_tightness():
    kr = np.array([5.0, 7.0])
    tb = C.tracking_bounds(kr, 0.02, 8.0, alpha=20.0)
    eps = np.sqrt(2 * 0.02 / 8.0)
    assert tb.eps == pytest.approx(eps) and tb.eps >= eps
    np.testing.assert_allclose(tb.position, eps / kr)
    np.testing.assert_allclose(tb.velocity, 2 * eps)
    np.testing.assert_allclose(tb.qd_a, eps)
    np.testing.assert_allclose(tb.qdd_a, 2 * kr * eps)
    # Worst case of edot = r - Kr e with |r| <= eps: r = +eps until e ~ eps/Kr, then -eps.
    dt, k = 1e-5, kr[0]
    e, worst_e, worst_edot = 0.0, 0.0, 0.0
    for step in range(int(2.0 / dt)):
        r = eps if step * dt < 1.5 else -eps
        edot = r - k * e
        e += dt * edot
        worst_e, worst_edot = max(worst_e, abs(e)), max(worst_edot, abs(edot))
    assert worst_e <= tb.position[0] and worst_e > 0.99 * tb.position[0]
    assert worst_edot <= tb.velocity[0] and worst_edot > 0.99 * tb.velocity[0]


def test_parameter_box_contains_model(robot):
    theta0, box = uncertainty.parameter_box(robot, robot.theta_e, robot.theta_e - 0.1, robot.theta_e + 0.1)
    assert np.all(box.contains(robot.theta)) and np.all(box.contains(theta0))
    assert isinstance(box, Interval) and np.any(box.hi[10:] > box.lo[10:])


def test_all_controllers_share_ports(robot):
    from safesysid.scenario import load_scenario
    from safesysid.systems.controller.systems import gains_from_scenario, make_controller

    gains = gains_from_scenario(load_scenario(), robot.n)
    n, p = robot.n, 14 * robot.n
    expected = {"desired": 3 * n, "state": 2 * n, "theta0": p, "theta_lower": p, "theta_upper": p}
    theta0, box = _box(robot, np.random.default_rng(6))
    for kind in ("armour", "pid", "adaptive", "adaptive_robust"):
        system = make_controller(kind, robot, gains, time_step=0.001)
        ports = {
            system.get_input_port(i).get_name(): system.get_input_port(i).size()
            for i in range(system.num_input_ports())
        }
        assert ports == expected
        assert system.GetOutputPort("torque").size() == n
        ctx = system.CreateDefaultContext()
        q = np.array([0.0, 0.26, 0.0, 2.0, 0.0, 0.9, 1.57])
        for name, value in (
            ("desired", np.concatenate([q, np.zeros(14)])),
            ("state", np.concatenate([q, np.zeros(7)])),
            ("theta0", theta0),
            ("theta_lower", box.lo),
            ("theta_upper", box.hi),
        ):
            system.GetInputPort(name).FixValue(ctx, value)
        u = system.GetOutputPort("torque").Eval(ctx)
        # At rest on the trajectory every law commands the nominal gravity + offset torque.
        np.testing.assert_allclose(u, C.ControllerDynamics(robot).gravity(q, theta0), atol=1e-9)


def test_armour_controller_never_commands_nan(robot, caplog):
    from safesysid.scenario import load_scenario
    from safesysid.systems.controller.systems import gains_from_scenario, make_controller

    system = make_controller("armour", robot, gains_from_scenario(load_scenario(), robot.n), time_step=0.001)
    ctx = system.CreateDefaultContext()
    q = np.array([0.0, 0.26, 0.0, 2.0, 0.0, 0.9, 1.57])
    bad = robot.theta.copy()
    bad[3] = np.nan
    for name, value in (
        ("desired", np.concatenate([q, np.zeros(14)])),
        ("state", np.concatenate([q + 0.01, np.zeros(7)])),
        ("theta0", bad),
        ("theta_lower", robot.theta),
        ("theta_upper", robot.theta),
    ):
        system.GetInputPort(name).FixValue(ctx, value)
    with caplog.at_level("WARNING"):
        u = system.GetOutputPort("torque").Eval(ctx)
    assert np.all(np.isfinite(u)) and "invalid theta" in caplog.text
