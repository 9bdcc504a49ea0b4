"""Algorithm 1 (systems/estimation/): data model, solver, provable interval, incremental use."""

import numpy as np
import pytest
from helpers import CENTRE, PAYLOADS, PRIOR, PRIOR_NOMINAL, n_trials
from safesysid.systems import estimation as E
from safesysid.systems.model import inertial
from safesysid.systems.model.payload import load_dumbbells, payload_theta_in_end_effector
from safesysid.systems.model.robot_model import MODELS_DIR


def true_theta(rng, robot, dumbbell, ratio=0.05):
    """Whole-robot truth: θ_r perturbed inside its ±ratio box, θ_e = end effector + payload."""
    theta = E.perturbed_robot_theta(rng, robot, ratio)
    theta_e = robot.theta_e + payload_theta_in_end_effector(dumbbell, robot.extra["grasp_point"])
    theta[robot.ee_slice] = theta_e
    return theta, theta_e


def run_online(robot, t, q, v, tau, settings=None, period_s=1.5):
    """Feed the log chunk by chunk and update every period (Algorithm 2's cadence)."""
    est = E.IncrementalEstimator(robot, settings=settings or E.EstimatorSettings())
    out = []
    edges = np.arange(t[0] + period_s, t[-1] + 1e-9, period_s)
    start = 0
    for edge in edges:
        stop = int(np.searchsorted(t, edge, side="right"))
        est.add(t[start:stop], q[start:stop], v[start:stop], tau[start:stop])
        start = stop
        out.append(est.update())
    return est, out


# ---- data model -----------------------------------------------------------------------------------
def test_segments_by_time_never_span_a_gap():
    rng = np.random.default_rng(1)
    steps = rng.uniform(0.0005, 0.0015, 3000)
    steps[1200] = 0.5  # a logging gap
    t = np.concatenate([[0.0], np.cumsum(steps)])
    bounds, next_start = E.segment_bounds(t, 0.1, 0.05)
    assert len(bounds) > 10
    for a, b in bounds:
        assert t[b] - t[a] >= 0.1 - 1e-12
        assert np.max(np.diff(t[a : b + 1])) <= 0.05  # never across the gap
        assert t[b - 1] - t[a] < 0.1  # ends at the first sample past the horizon
    shared = bounds[1:, 0] == bounds[:-1, 1]
    assert shared.sum() == len(bounds) - 2  # contiguous except across the gap
    assert next_start == bounds[-1, 1]


@pytest.mark.parametrize("integration", ["trapezoid", "euler"])
def test_integrated_rate_regressor_matches_per_sample_regressor(robot, integration):
    rng = np.random.default_rng(2)
    t, q, v, _ = E.fourier_trajectory(rng, robot, 0.35, rate_hz=1000.0, centre=CENTRE)
    t = t + rng.uniform(0, 2e-4, len(t)) * (np.arange(len(t)) > 0)  # uneven steps
    bounds, _ = E.segment_bounds(t, 0.1, 0.05)
    fast = E.integrated_rate_regressor(robot.tree, q, v, t, bounds, integration=integration)
    wc = robot.momentum_rate_regressor(q, v)[..., : 10 * robot.n]
    ref = np.stack(
        [np.tensordot(E.sample_weights(t, a, b, integration=integration), wc[a : b + 1], 1) for a, b in bounds]
    )
    assert np.abs(fast - ref).max() <= 1e-12 * np.abs(ref).max()


@pytest.mark.parametrize(
    "integration, rate_hz, period_s",
    [("trapezoid", 1000.0, None), ("euler", 1000.0, None), ("trapezoid", 200.0, 0.5), ("euler", 100.0, 1.0)],
)
def test_quadrature_bound_covers_the_integration_error(robot, dumbbells, integration, rate_hz, period_s):
    """Noise-free held-torque log and the true θ: ∫τ dt is exact (left sum of the held torque), so
    every row's residual is the quadrature error of ∫W_c θ dt; it is inside the bound, also at
    100-200 Hz on a fast motion where that error is large. The trapezoid on the held torque (the
    old rule) leaves an error of h/2·|τ_b − τ_a| per segment that no bound carries."""
    rng = np.random.default_rng(3)
    theta, theta_e = true_theta(rng, robot, dumbbells["8lb"])
    t, q, v, _, tau = E.simulate_log(
        rng, robot, theta, duration_s=3.0, rate_hz=rate_hz, centre=CENTRE, period_s=period_s
    )
    settings = E.EstimatorSettings(integration=integration, horizon_s=max(0.1, 10 / rate_hz), hold_period_s=1 / rate_hz)
    bounds, _ = E.segment_bounds(t, settings.horizon_s, settings.segment_gap_s())
    box = (theta, 0.05 * np.abs(theta))  # the bound holds for every θ of a box around the truth
    rows = E.build_segment_rows(robot, t, q, v, tau, bounds, settings, theta_box=box)
    lhs = rows.Y @ theta_e + np.einsum("snk,k->sn", rows.D_r, theta[robot.rest_mask()])
    resid = lhs - rows.T
    assert np.all(np.abs(resid) <= rows.quad)
    assert np.abs(resid).max() > 1e-3 * rows.quad.max()  # a real error, not a zero
    trapezoid_torque = E.segment_sums(tau, t, bounds, integration="trapezoid")
    assert np.any(np.abs(lhs - trapezoid_torque) > rows.quad)


def test_quadrature_bound_grows_with_the_box(robot, dumbbells):
    """The rates behind the bound are taken over the whole parameter box, so a wider box never
    gives a smaller bound (monotone), and a zero box gives the nominal integrand's bound."""
    rng = np.random.default_rng(4)
    theta, _ = true_theta(rng, robot, dumbbells["6lb"])
    t, q, v, _, tau = E.simulate_log(rng, robot, theta, duration_s=1.0, centre=CENTRE)
    settings = E.EstimatorSettings()
    bounds, _ = E.segment_bounds(t, settings.horizon_s, settings.segment_gap_s())
    quads = [
        E.build_segment_rows(robot, t, q, v, tau, bounds, settings, theta_box=(theta, k * 0.05 * np.abs(theta))).quad
        for k in (0, 1, 2)
    ]
    assert np.all(quads[0] <= quads[1]) and np.all(quads[1] <= quads[2]) and np.any(quads[0] < quads[2])


# ---- solver and sensitivity ---------------------------------------------------------------------
def test_cost_gradient_and_hessian_are_exact():
    rng = np.random.default_rng(5)
    Y = rng.normal(size=(60, 10))
    U = rng.normal(size=60)
    A, b, c = E.ls_cost_terms(Y, U)
    eta = rng.normal(scale=0.3, size=10)
    J, g, H = E.cost_grad_hess(eta, A, b, c)
    J2, g2 = E.cost_and_gradient(eta, A, b, c)
    theta = inertial.log_cholesky_to_theta(eta)
    assert J == pytest.approx(0.5 * np.sum((Y @ theta - U) ** 2), rel=1e-10)
    assert J2 == pytest.approx(J, rel=1e-12) and np.allclose(g2, g, rtol=1e-10, atol=1e-12)
    h = 1e-6
    for k in range(10):
        d = np.zeros(10)
        d[k] = h
        gp, gm = E.cost_grad_hess(eta + d, A, b, c)[1], E.cost_grad_hess(eta - d, A, b, c)[1]
        assert g[k] == pytest.approx(
            (E.cost_grad_hess(eta + d, A, b, c)[0] - E.cost_grad_hess(eta - d, A, b, c)[0]) / (2 * h),
            rel=1e-5,
            abs=1e-6,
        )
        assert np.allclose(H[:, k], (gp - gm) / (2 * h), rtol=1e-5, atol=1e-5)


def test_solver_recovers_consistent_optimum_and_ift_equals_linear_map(robot):
    """Interior optimum: θ0 = Y⁺U, and the paper's implicit-function sensitivity equals the
    constant linear map Y⁺ ∂U/∂m (the residual-curvature term vanishes at the optimum)."""
    rng = np.random.default_rng(6)
    theta_true = robot.theta_e + payload_theta_in_end_effector(
        load_dumbbells(MODELS_DIR / "dumbbells.yaml")["5lb"], robot.extra["grasp_point"]
    )
    Y = rng.normal(size=(80, 10)) * np.r_[5.0, 1, 1, 1, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3]
    U = Y @ theta_true + rng.normal(scale=1e-3, size=80)
    A, b, c = E.ls_cost_terms(Y, U)
    sol = E.solve_log_cholesky(A, b, c, np.zeros(10))
    theta_ls = np.linalg.lstsq(Y, U, rcond=None)[0]
    assert inertial.is_physically_consistent(theta_ls)
    assert sol.success
    assert np.allclose(sol.theta, theta_ls, rtol=1e-7, atol=1e-9)
    dU_dm = rng.normal(size=(80, 30))
    sens = E.ift_sensitivity(sol.eta, A, b, dU_dm_Y=Y.T @ dU_dm)
    assert np.allclose(sens, np.linalg.pinv(Y) @ dU_dm, rtol=1e-6, atol=1e-9)


def test_solver_stays_finite_when_the_lmi_is_active():
    """Unconstrained optimum not physically consistent: infimum on the LMI boundary; the solver
    returns a finite, consistent θ close to the best consistent cost."""
    rng = np.random.default_rng(7)
    theta_bad = np.array([1.0, 0, 0, 0, -0.1, 0.2, 0.2, 0, 0, 0])  # negative inertia
    Y = rng.normal(size=(50, 10))
    A, b, c = E.ls_cost_terms(Y, Y @ theta_bad)
    sol = E.solve_log_cholesky(A, b, c, np.zeros(10))
    assert np.all(np.isfinite(sol.theta)) and inertial.is_physically_consistent(sol.theta)
    proj = E.nearest_consistent(theta_bad)
    assert sol.cost <= E.cost_grad_hess(inertial.theta_to_log_cholesky(proj), A, b, c)[0] + 1e-9


# ---- the guarantee ----------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("payload", PAYLOADS)
def test_truth_inside_interval_in_every_randomized_run(robot, dumbbells, payload):
    """Gen3 + dumbbell, random exciting motion, θ_r inside ±5%, uniform torque noise inside the
    declared bound: the truth is inside [θ_e] after every update of every run; θ0's mass within
    2%; mass interval within ±0.5 kg after 7.5 s at 1 kHz."""
    runs = n_trials(2, 50)
    mass_err, half = [], []
    for seed in range(runs):
        rng = np.random.default_rng(1000 * PAYLOADS.index(payload) + seed)
        theta, theta_e = true_theta(rng, robot, dumbbells[payload])
        t, q, v, tau, _ = E.simulate_log(rng, robot, theta, duration_s=7.5, rate_hz=1000.0, centre=CENTRE)
        _, history = run_online(robot, t, q, v, tau)
        for k, est in enumerate(history):
            assert est.consistent, est.message
            assert est.contains(theta_e), (seed, k, est.lower, est.upper, theta_e)
            assert np.all(est.lower <= est.upper)
        final = history[-1]
        mass_err.append(abs(final.theta_e[0] - theta_e[0]) / theta_e[0])
        half.append(0.5 * (final.upper[0] - final.lower[0]))
    assert max(mass_err) <= 0.02, mass_err
    assert max(half) <= 0.5, half


def uneven_held_log(rng, robot, theta, duration_s=7.5):
    """A held-torque log on an uneven grid (the controller's period jitters, each sample holds
    until the next) with a 0.5 s logging gap: (t, q, v, τ_meas, θ_e)."""
    t_grid, motion = E.fourier_motion(rng, robot, duration_s, 1000.0, centre=CENTRE)
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.0006, 0.0014, int(duration_s / 1e-3)))])
    t = t[t <= t_grid[-1]]
    t = t[(t < 3.0) | (t > 3.5)]  # the gap: no samples, the torque held over it is unknown
    q, v, _ = motion(t)
    tau = E.held_torque(robot, motion, t, theta=theta)
    tau_meas = tau + rng.uniform(-1, 1, tau.shape) * (0.025 * np.abs(tau) + 0.05)
    return t, q, v, tau_meas


@pytest.mark.parametrize("integration", ["trapezoid", "euler"])
def test_held_torque_with_uneven_steps_and_gaps(robot, dumbbells, integration):
    rng = np.random.default_rng(11)
    theta, theta_e = true_theta(rng, robot, dumbbells["7lb"])
    t, q, v, tau = uneven_held_log(rng, robot, theta)
    settings = E.EstimatorSettings(integration=integration, hold_period_s=0.0014)
    ie = E.IncrementalEstimator(robot, settings=settings)
    ie.add(t, q, v, tau)
    est = ie.update()
    assert est.consistent and est.contains(theta_e)
    for a, b in zip(ie.rows.start_index, ie.rows.end_index):
        assert np.max(np.diff(t[a : b + 1])) <= min(settings.max_gap_s, 1.5 * settings.hold_period_s)


@pytest.mark.parametrize("declared", [{"hold_period_s": 1e-3}, {}], ids=["declared", "library_default"])
def test_held_torque_segments_never_span_a_lost_sample(robot, dumbbells, declared):
    """A held sample that was not logged has an unknown torque: a step longer than 1.5 hold
    periods ends the segment (here one dropped sample in twenty), also with the library's
    default settings (no hold period given: the 1 kHz controller's step, never "no rule")."""
    rng = np.random.default_rng(12)
    theta, _ = true_theta(rng, robot, dumbbells["5lb"])
    t, q, v, tau, _ = E.simulate_log(rng, robot, theta, duration_s=3.0, rate_hz=1000.0, centre=CENTRE)
    keep = np.ones(len(t), bool)
    keep[rng.choice(np.arange(1, len(t)), len(t) // 20, replace=False)] = False
    ie = E.IncrementalEstimator(robot, settings=E.EstimatorSettings(**declared))
    ie.add(t[keep], q[keep], v[keep], tau[keep])
    tk = t[keep]
    assert len(ie.rows) > 0
    for a, b in zip(ie.rows.start_index, ie.rows.end_index):
        assert np.max(np.diff(tk[a : b + 1])) < 1.5e-3


def test_a_log_slower_than_the_hold_period_is_refused_with_a_hint(robot):
    """A 100 Hz log declared as held at 1 kHz: every step loses held samples, so no segment
    forms; the error says which setting to change."""
    rng = np.random.default_rng(14)
    t, q, v, tau, _ = E.simulate_log(rng, robot, robot.theta, duration_s=2.0, rate_hz=100.0, centre=CENTRE)
    est = E.IncrementalEstimator(robot, settings=E.EstimatorSettings(hold_period_s=1e-3))
    est.add(t, q, v, tau)
    with pytest.raises(E.EstimatorError, match="hold_period_s"):
        est.update()


def test_continuous_torque_with_dropped_samples_and_its_rate_check(robot, dumbbells):
    """A torque sampled from a continuous signal (inverse dynamics at the sample instants), 20 %
    of the samples dropped and a 0.5 s gap: with a declared rate limit above the true one the
    interval contains the truth; declared 10x below it, the data contradict it (flagged)."""
    rng = np.random.default_rng(13)
    theta, theta_e = true_theta(rng, robot, dumbbells["7lb"])
    t, q, v, tau, tau_true = E.simulate_log(
        rng, robot, theta, duration_s=7.5, rate_hz=1000.0, centre=CENTRE, torque="sampled"
    )
    keep = np.ones(len(t), bool)
    keep[rng.choice(len(t), 1500, replace=False)] = False
    keep[3000:3500] = False
    keep[0] = True
    true_rate = np.max(np.abs(np.diff(tau_true, axis=0)) / np.diff(t)[:, None])
    ok = E.EstimatorSettings(torque_signal="continuous", torque_rate_limit_Nm_s=1.2 * true_rate)
    est = E.identify(robot, t[keep], q[keep], v[keep], tau[keep], settings=ok)
    assert est.consistent and est.contains(theta_e), est.message
    low = E.EstimatorSettings(torque_signal="continuous", torque_rate_limit_Nm_s=0.1 * true_rate)
    est = E.identify(robot, t[keep], q[keep], v[keep], tau[keep], settings=low)
    assert not est.consistent and "faster than the declared" in " ".join(est.problems)


def test_bound_is_not_vacuous_containment_fails_when_noise_exceeds_it(robot, dumbbells):
    """Same experiment with torque noise 10x the declared bound: the truth falls outside the
    interval or the estimator reports the data inconsistent, in most runs."""
    failures = 0
    runs = 4
    for seed in range(runs):
        rng = np.random.default_rng(500 + seed)
        theta, theta_e = true_theta(rng, robot, dumbbells["8lb"])
        t, q, v, tau, _ = E.simulate_log(
            rng, robot, theta, duration_s=7.5, rate_hz=1000.0, centre=CENTRE, noise_scale=10.0
        )
        _, history = run_online(robot, t, q, v, tau)
        if any((not e.contains(theta_e)) or (not e.consistent) for e in history):
            failures += 1
    assert failures >= runs - 1


def test_theta_r_outside_its_box_is_caught(robot, dumbbells):
    """θ_r perturbed by 40% while the estimator declares 5%: containment fails or is flagged."""
    rng = np.random.default_rng(21)
    theta, theta_e = true_theta(rng, robot, dumbbells["8lb"], ratio=0.0)
    theta[robot.rest_mask()] *= 1.4
    t, q, v, tau, _ = E.simulate_log(rng, robot, theta, duration_s=7.5, rate_hz=1000.0, centre=CENTRE)
    _, history = run_online(robot, t, q, v, tau)
    assert any((not e.contains(theta_e)) or (not e.consistent) for e in history)


def test_set_membership_lp_is_certified_and_tighter(robot, dumbbells):
    rng = np.random.default_rng(31)
    theta, theta_e = true_theta(rng, robot, dumbbells["6lb"])
    t, q, v, tau, _ = E.simulate_log(rng, robot, theta, duration_s=4.5, rate_hz=1000.0, centre=CENTRE)
    plain = E.identify(robot, t, q, v, tau, settings=E.EstimatorSettings(set_membership="none"))
    full = E.identify(robot, t, q, v, tau, settings=E.EstimatorSettings(set_membership="all"))
    assert full.contains(theta_e) and plain.contains(theta_e)
    assert np.all(full.widths <= plain.widths + 1e-12)
    assert full.widths[0] < 0.9 * plain.widths[0]


def test_a_windowed_set_membership_lp_keeps_its_size_and_the_truth(robot, dumbbells, monkeypatch):
    """estimator.set_membership_window_s: the LP takes the last window's segments only, inside the
    published data box: its size stops growing with the data, the box still holds the truth and
    the mass (the LP's parameter) is never looser than without the LP."""
    from safesysid.systems.estimation import enclosure

    rng = np.random.default_rng(33)
    theta, theta_e = true_theta(rng, robot, dumbbells["6lb"])
    t, q, v, tau, _ = E.simulate_log(rng, robot, theta, duration_s=6.0, rate_hz=1000.0, centre=CENTRE)
    sizes = []

    def counted(c, A_ub, *args, **kwargs):  # two rows per joint and segment
        sizes.append(len(A_ub) // (2 * robot.n))
        return lp_min(c, A_ub, *args, **kwargs)

    lp_min = enclosure.certified_lp_min
    monkeypatch.setattr(enclosure, "certified_lp_min", counted)
    windowed = E.EstimatorSettings(set_membership="mass", set_membership_window_s=1.0)
    _, history = run_online(robot, t, q, v, tau, settings=windowed)
    _, plain = run_online(robot, t, q, v, tau, settings=E.EstimatorSettings(set_membership="none"))
    print("LP segments per update:", sizes)
    sizes = sizes[::2]  # the mass: 2 LPs per update
    assert sizes[0] > 10 and max(sizes[1:]) <= 11 < len(history) * 10  # 1 s of 0.1 s segments
    for est, loose in zip(history, plain):
        assert est.consistent and est.contains(theta_e)
        assert est.widths[0] <= loose.widths[0] + 1e-12
    assert history[-1].widths[0] < 0.95 * plain[-1].widths[0]


def test_interval_reports_widths_cond_and_radii(robot, dumbbells):
    rng = np.random.default_rng(41)
    theta, theta_e = true_theta(rng, robot, dumbbells["5lb"])
    t, q, v, tau, _ = E.simulate_log(rng, robot, theta, duration_s=3.0, rate_hz=1000.0, centre=CENTRE)
    est = E.identify(robot, t, q, v, tau)
    assert np.isfinite(est.cond_Y) and est.cond_Y >= 1
    assert est.widths.shape == (10,) and np.all(est.widths > 0)
    for part in (est.radius_torque, est.radius_theta_r, est.radius_quadrature, est.radius_rounding):
        assert np.all(part >= 0)
    assert est.case in ("interior", "interior_at_m", "lmi_active")
    doc = est.to_json()
    assert len(doc["nominal"]) == 10 and doc["names"][0] == "m"
    # Whole-robot outputs: θ_r nominal and its box, end effector replaced.
    assert np.allclose(est.theta[robot.rest_mask()], robot.theta[robot.rest_mask()])
    assert np.all(est.theta_lower <= est.theta) or est.case != "interior"
    assert np.allclose(est.theta_lower[robot.ee_slice], est.lower)


# ---- incremental use, intersection, bad input ------------------------------------------------------
def test_incremental_chunks_give_the_batch_segments(robot, dumbbells):
    rng = np.random.default_rng(51)
    theta, _ = true_theta(rng, robot, dumbbells["4lb"])
    t, q, v, tau, _ = E.simulate_log(rng, robot, theta, duration_s=3.0, rate_hz=1000.0, centre=CENTRE)
    batch = E.IncrementalEstimator(robot)
    batch.add(t, q, v, tau)
    inc = E.IncrementalEstimator(robot)
    cuts = np.sort(rng.choice(np.arange(1, len(t)), 17, replace=False))
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(t)]):
        inc.add(t[a:b], q[a:b], v[a:b], tau[a:b])
    assert len(inc.rows) == len(batch.rows)
    assert np.array_equal(inc.rows.start_index, batch.rows.start_index)
    assert np.allclose(inc.rows.Y, batch.rows.Y, rtol=1e-12, atol=1e-12)
    assert np.allclose(inc.rows.T, batch.rows.T, rtol=1e-12, atol=1e-12)
    assert np.array_equal(inc.rows.shared_prev, batch.rows.shared_prev)
    e1, e2 = batch.update(), inc.update()
    assert np.allclose(e1.lower, e2.lower, rtol=1e-9, atol=1e-12)


def test_intersection_never_returns_an_inverted_interval(robot, dumbbells):
    rng = np.random.default_rng(61)
    theta, theta_e = true_theta(rng, robot, dumbbells["8lb"])
    t, q, v, tau, _ = E.simulate_log(rng, robot, theta, duration_s=3.0, rate_hz=1000.0, centre=CENTRE)
    wrong_prior = (np.r_[10.0, -np.ones(9)], np.r_[11.0, np.ones(9)])  # excludes the true mass
    est = E.identify(robot, t, q, v, tau, prior=wrong_prior)
    assert not est.consistent and "inconsistent" in est.message
    assert np.all(est.lower <= est.upper)
    good_prior = (theta_e - 0.5, theta_e + 0.5)
    est = E.identify(robot, t, q, v, tau, prior=good_prior)
    assert est.consistent and est.contains(theta_e)
    assert np.all(est.lower >= good_prior[0]) and np.all(est.upper <= good_prior[1])


def test_inconsistent_data_keep_the_last_consistent_box(robot, dumbbells):
    """A torque-sensor offset of 1 N·m appears at 4.5 s (outside the declared bound). The update
    that sees it reports the inconsistency, consistency stays latched off, and the published box
    is the last consistent one from then on: never wider, never outside the prior, and still
    around the truth. (HEAD published the faulty intersection, then the hull of the two boxes:
    truth outside from 4.5 s, mass upper 5.35 kg > the prior's 5.2 kg at 7.5 s.)"""

    rng = np.random.default_rng(5)
    theta, theta_e = true_theta(rng, robot, dumbbells["8lb"], ratio=0.0)
    t, q, v, tau, _ = E.simulate_log(rng, robot, theta, duration_s=7.5, rate_hz=1000.0, centre=CENTRE)
    tau[t >= 4.5] += 1.0
    est = E.IncrementalEstimator(robot, prior=PRIOR, prior_nominal=PRIOR_NOMINAL)
    published, flags = PRIOR, []
    for a, b in zip(range(0, 7501, 1500), range(1500, 7502, 1500)):
        est.add(t[a:b], q[a:b], v[a:b], tau[a:b])
        e = est.update()
        assert np.all(e.lower >= published[0]) and np.all(e.upper <= published[1])
        assert e.contains(theta_e)
        if flags and not flags[-1]:
            np.testing.assert_array_equal(e.lower, published[0])
            np.testing.assert_array_equal(e.upper, published[1])
        published = (e.lower, e.upper)
        flags.append(e.consistent)
    assert flags == [True, True, True, False, False]
    assert not est.consistent and any("inconsistent" in m for m in est.messages)


def test_disjoint_enclosures_do_not_publish_the_gap(robot, dumbbells):
    """Torque noise 10x the declared bound: when the two least-squares enclosures (or the LP) do
    not meet, the published box is the prior, not the gap between them."""

    for seed in range(4):
        rng = np.random.default_rng(500 + seed)
        theta, theta_e = true_theta(rng, robot, dumbbells["8lb"])
        t, q, v, tau, _ = E.simulate_log(
            rng, robot, theta, duration_s=3.0, rate_hz=1000.0, centre=CENTRE, noise_scale=10.0
        )
        e = E.identify(robot, t, q, v, tau, prior=PRIOR, prior_nominal=PRIOR_NOMINAL)
        if not e.consistent:
            np.testing.assert_array_equal(e.lower, PRIOR[0])
            np.testing.assert_array_equal(e.upper, PRIOR[1])
            np.testing.assert_array_equal(e.theta_e, PRIOR_NOMINAL)
            return
    pytest.fail("no inconsistency with 10x the declared noise")


def test_bad_input_is_rejected(robot):
    rng = np.random.default_rng(71)
    t, q, v, _ = E.fourier_trajectory(rng, robot, 1.0, rate_hz=1000.0, centre=CENTRE)
    tau = np.zeros_like(q)
    est = E.IncrementalEstimator(robot)
    with pytest.raises(E.EstimatorError, match="joints"):
        est.add(t, q[:, :6], v, tau)
    bad = q.copy()
    bad[5, 2] = np.nan
    with pytest.raises(E.EstimatorError, match="NaN"):
        est.add(t, bad, v, tau)
    t_bad = t.copy()
    t_bad[10] = t_bad[9]
    with pytest.raises(E.EstimatorError, match="increasing"):
        est.add(t_bad, q, v, tau)
    short = E.IncrementalEstimator(robot)
    short.add(t[:50], q[:50], v[:50], tau[:50])  # 0.05 s: not one 0.1 s segment
    with pytest.raises(E.EstimatorError, match="too little data"):
        short.update()


def test_table_v_observation_matrix_tends_to_dt_times_w(robot):
    """Table V's construction: with h = 1 sample, Y ≈ Δt·W (end-effector columns)."""
    from safesysid.systems.model import regressors
    from table_v import observation_matrix

    rng = np.random.default_rng(81)
    t, q, v, a = E.fourier_trajectory(rng, robot, 0.5, rate_hz=1000.0, period_s=1.0, centre=CENTRE)
    ee = [robot.end_effector]
    wm = regressors.momentum_regressor(robot.tree, q, v, bodies=ee)
    wc = regressors.momentum_rate_regressor(robot.tree, q, v, bodies=ee)
    y1 = observation_matrix(wm, wc, 1e-3, 1).reshape(-1, robot.n, 10)
    w = regressors.standard_regressor(robot.tree, q, v, a, bodies=ee)
    w_mid = 0.5 * (w[:-1] + w[1:])
    assert np.abs(y1 - 1e-3 * w_mid).max() < 1e-3 * 1e-3 * np.abs(w).max()
    y50 = observation_matrix(wm, wc, 1e-3, 50)
    assert y50.shape == (10 * robot.n, 10)
