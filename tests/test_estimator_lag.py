"""estimator.torque_lag_s: a torque sensor that low-passes its reading (first order, time
constant d, the noise inside the declared bound before the filter, as the simulated arm's
TorqueSensor) is undone exactly, so the interval keeps containing the truth with the noise AT the
declared bound; ignoring the lag breaks it (tests/test_estimator_adversarial.py's cases, lagged).
"""

import dataclasses

import numpy as np
import pytest
from helpers import FULL, PRIOR, PRIOR_NOMINAL, n_trials
from safesysid.systems import estimation as E
from safesysid.systems.estimation.lag import LagInverse, unlag
from test_estimator_adversarial import make_case, outside

LAG_S = 0.11  # the lag the diagnosis finds on the real Gen3 logs (README)


def lagged(t, raw, lag_s):
    """The filter state a first-order sensor logs at each t_k: y_0 = r_0 (started steady),
    y_k+1 = a y_k + (1 − a) r_k with r_k held over [t_k, t_k+1] (the exact solution of
    d y' + y = r), written out sample by sample."""
    y = np.empty_like(raw)
    y[0] = raw[0]
    for k in range(len(t) - 1):
        a = np.exp(-(t[k + 1] - t[k]) / lag_s)
        y[k + 1] = a * y[k] + (1 - a) * raw[k]
    return y


def settings(lag_s, set_membership="all"):
    return dataclasses.replace(E.EstimatorSettings(), torque_lag_s=lag_s, set_membership=set_membership)


def test_unlag_recovers_each_steps_reading_and_streams_one_sample_late():
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.0009, 0.0011, 400))  # uneven steps: a_k per step
    raw = rng.normal(0, 10, (400, 7))
    y = lagged(t, raw, LAG_S)
    assert np.max(np.abs(y - raw)) > 5  # the lag changes the signal a lot
    np.testing.assert_allclose(unlag(t, y, LAG_S), raw[:-1], rtol=0, atol=1e-10)
    # Streamed in uneven chunks: the same readings, each once, the last one still waiting.
    inverse = LagInverse(LAG_S, max_step_s=0.0015)
    q = np.zeros((400, 7))
    parts = [inverse.push(t[a:b], q[a:b], q[a:b], y=y[a:b]) for a, b in ((0, 1), (1, 2), (2, 137), (137, 400))]
    got_t = np.concatenate([p[0] for p in parts])
    got_r = np.concatenate([p[3] for p in parts])
    assert not np.concatenate([p[4] for p in parts]).any()  # one lag: exact, no radius
    np.testing.assert_array_equal(got_t, t[:-1])
    np.testing.assert_allclose(got_r, raw[:-1], rtol=0, atol=1e-10)
    # A lost sample: the reading before the gap is unknown, so that sample is dropped.
    inverse = LagInverse(LAG_S, max_step_s=0.0015)
    keep = np.ones(400, bool)
    keep[200] = False
    out_t, _, _, out_r, _ = inverse.push(t[keep], q[keep], q[keep], y=y[keep])
    assert 199 not in np.searchsorted(t, out_t) and len(out_t) == 397
    np.testing.assert_allclose(out_r, raw[:-1][np.isin(t[:-1], out_t)], rtol=0, atol=1e-10)


def test_rows_of_a_lagged_log_are_the_rows_of_the_readings(robot, dumbbells):
    """Same segments, same ∫τ and radii as the unlagged readings (one sample later at most)."""
    t, q, v, tau_meas, *_ = make_case(robot, dumbbells, 3)
    plain = E.IncrementalEstimator(robot, settings=settings(0.0), prior=PRIOR, prior_nominal=PRIOR_NOMINAL)
    lag = E.IncrementalEstimator(robot, settings=settings(LAG_S), prior=PRIOR, prior_nominal=PRIOR_NOMINAL)
    plain.add(t, q, v, tau_meas)
    y = lagged(t, tau_meas, LAG_S)
    for a, b in ((0, 1), (1, 1500), (1500, len(t))):
        lag.add(t[a:b], q[a:b], v[a:b], y[a:b])
    S = len(lag.rows)
    assert S >= len(plain.rows) - 1 and S > 20
    for name in ("T", "r_inner", "r_first", "quad", "Y"):
        np.testing.assert_allclose(getattr(lag.rows, name), getattr(plain.rows, name)[:S], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("block", range(2))
def test_truth_inside_with_a_lagged_sensor_and_noise_at_the_bound(robot, dumbbells, block):
    """16 adversarial cases in CI (noise at the declared bound before the filter, θ_r at vertices,
    the worst-case signs of a left inverse), 100 with SAFESYSID_FULL=1: with the lag declared the
    truth is inside every published interval (two updates, all ten LPs) and the data are
    consistent; the same lagged logs with the lag ignored break the guarantee."""
    per_block = n_trials(8, 50)
    bad, ignored_broken, ignored_inconsistent = [], 0, 0
    for index in range(block * per_block, (block + 1) * per_block):
        t, q, v, tau_meas, _, theta_e, what = make_case(robot, dumbbells, index)
        y = lagged(t, tau_meas, LAG_S)
        for lag_s in (LAG_S, 0.0):
            est = E.IncrementalEstimator(robot, settings=settings(lag_s), prior=PRIOR, prior_nominal=PRIOR_NOMINAL)
            for a, b in ((0, 1500), (1500, len(t))):
                est.add(t[a:b], q[a:b], v[a:b], y[a:b])
                e = est.update()
                ok = e.contains(theta_e) and e.consistent
                if lag_s and not ok:
                    bad.append(
                        f"{what}: inside={e.contains(theta_e)} consistent={e.consistent} "
                        f"outside={outside(e, theta_e):.3g}"
                    )
            ignored_broken += not lag_s and not ok
            ignored_inconsistent += not lag_s and not e.consistent
    print(
        f"block {block}: lag declared, {len(bad)} of {2 * per_block} updates fail; lag ignored, "
        f"{ignored_broken}/{per_block} cases break ({ignored_inconsistent} flag consistent off)"
    )
    assert not bad, f"{len(bad)} failures:\n" + "\n".join(bad)
    assert ignored_broken >= per_block // 2, "the lag this test declares must matter: ignored, it should break"


def test_lag_needs_a_held_torque(robot):
    bad = dataclasses.replace(E.EstimatorSettings(), torque_lag_s=0.1, torque_signal="continuous")
    with pytest.raises(E.EstimatorError, match="torque_lag_s"):
        E.IncrementalEstimator(robot, settings=bad)


def online_first_update(*texts):
    """The online diagram of experiment (a), 8 lb, the real arm's sensor lagging LAG_S, after its
    first update (1.6 s), with the scenario texts given: (its IncrementalEstimator, its update
    history, the arm's true θ)."""
    from helpers import simulate_online
    from safesysid.online import build_online
    from safesysid.scenario import SCENARIOS_DIR, load_scenario

    lagged_sensor = f"plant: {{effects: {{torque_sensor_lag_s: {LAG_S}}}}}"
    scene = load_scenario(
        SCENARIOS_DIR / "experiment_a.yaml", overrides=["payload: {dumbbell: 8lb}", lagged_sensor, *texts]
    )
    built = build_online(scene, "ours")
    sub = built.estimator.GetMyContextFromRoot(simulate_online(built, scene, 1.6))
    return built.estimator.estimator(sub), built.estimator.history(sub), built.arm.true_theta()


@pytest.mark.parametrize("declared", [True, False])
def test_online_estimator_with_the_real_arms_lagged_sensor(declared):
    """In the online diagram (experiment (a), 8 lb) the real arm's TorqueSensor lags 0.11 s (the
    real logs' figure): with estimator.torque_lag_s declared, the first update (1.5 s) is
    consistent and contains the truth; ignored, the data contradict the declared noise bound."""
    estimator, history, theta = online_first_update(*([f"estimator: {{torque_lag_s: {LAG_S}}}"] if declared else []))
    est = estimator.estimate
    assert est is not None and len(history) == 1
    if declared:
        assert est.consistent and est.contains(theta[estimator.robot.ee_slice]) and est.upper[0] - est.lower[0] < 1.5
    else:
        assert not est.consistent


def test_the_lag_matches_the_real_arms_sensor_exactly():
    """Noise-free online diagram (experiment (a), 8 lb, 1.6 s, the real arm's 0.11 s sensor lag):
    with the lag declared every row of the estimator holds with the true parameters within its
    quadrature term alone (the readings are recovered exactly); declared 10 % off, rows leave it
    by far."""

    def worst_row(lag_s):
        est, _, theta = online_first_update("noise: {distribution: none}", f"estimator: {{torque_lag_s: {lag_s}}}")
        rows, robot = est.rows, est.robot
        residual = rows.Y @ theta[robot.ee_slice] + rows.D_r @ theta[robot.rest_mask()] - rows.T
        return float(np.max(np.abs(residual) / (rows.quad + 1e-9))), len(rows)

    (exact, count), (off, _) = worst_row(LAG_S), worst_row(0.9 * LAG_S)
    print(f"worst |row residual| / quadrature term: {exact:.3g} (lag declared), {off:.3g} (10 % off)")
    assert count >= 14 and exact <= 1.0 and off > 10.0


def declared_lag_case(robot, dumbbells, index, true_lag_s, declared, set_membership="all"):
    """Adversarial case `index` (noise at the bound before the filter) logged through a sensor
    lagging true_lag_s, estimated with estimator.torque_lag_s = declared (two updates, all ten
    LPs): [(inside, consistent, mass width)] per update."""
    t, q, v, tau_meas, _, theta_e, _ = make_case(robot, dumbbells, index)
    y = lagged(t, tau_meas, true_lag_s)
    est = E.IncrementalEstimator(
        robot, settings=settings(declared, set_membership), prior=PRIOR, prior_nominal=PRIOR_NOMINAL
    )
    out = []
    for a, b in ((0, 1500), (1500, len(t))):
        est.add(t[a:b], q[a:b], v[a:b], y[a:b])
        e = est.update()
        out.append((e.contains(theta_e), e.consistent, float(e.widths[0])))
    return out


def test_a_near_miss_lag_as_one_value_breaks_and_the_interval_holds(robot, dumbbells):
    """The break the interval form closes: true lag 0.110 s declared 0.1095 s (0.5 % off, one
    value), noise at the bound (case 5, worst_map): the first update publishes a box without the
    truth marked consistent. (5 % off, the 16 cases of this file latch `consistent` off on their
    first update.) Declared [0.105, 0.115] instead, both updates hold the truth, consistent."""
    near_miss = declared_lag_case(robot, dumbbells, 5, 0.110, 0.1095)
    assert near_miss[0][1] and not near_miss[0][0], near_miss
    interval = declared_lag_case(robot, dumbbells, 5, 0.110, [0.105, 0.115])
    assert all(inside and consistent for inside, consistent, _ in interval), interval


def lag_interval_cases(robot, dumbbells, half_width, true_lag, count):
    """[(case, true lag, [(inside, consistent, mass width)] per update)] for
    estimator.torque_lag_s = 0.11 (1 ∓ half_width); true_lag(rng, lo, hi) draws the sensor's lag."""
    lo, hi = LAG_S * (1 - half_width), LAG_S * (1 + half_width)
    rng = np.random.default_rng(31)
    out = []
    for index in range(count):
        d = true_lag(rng, index, lo, hi)
        out.append((index, d, declared_lag_case(robot, dumbbells, index, d, [lo, hi])))
    return out


@pytest.mark.parametrize("half_width", [0.0, 0.05, 0.2])
def test_truth_inside_for_any_true_lag_in_the_declared_interval(robot, dumbbells, half_width):
    """estimator.torque_lag_s: [lo, hi] = 0.11 (1 ∓ half_width), the true lag drawn inside (its
    ends included), noise at the bound: every published box holds the truth, consistent. 6 cases
    per width in CI, 50 with SAFESYSID_FULL=1 (prints the final mass width, the width cost)."""
    inside_draw = lambda rng, index, lo, hi: (lo, hi, rng.uniform(lo, hi))[index % 3]  # noqa: E731
    cases = lag_interval_cases(robot, dumbbells, half_width, inside_draw, n_trials(6, 50))
    bad = [f"case {i} lag {d:.5f}: {r}" for i, d, r in cases if not all(a and b for a, b, _ in r)]
    widths = [r[-1][2] for _, _, r in cases]
    print(
        f"\n±{half_width:.0%}: {len(bad)}/{len(cases)} cases fail; final mass width median {np.median(widths):.3f} kg"
    )
    assert not bad, "\n".join(bad)


@pytest.mark.skipif(not FULL, reason="a measurement (SAFESYSID_FULL=1)")
@pytest.mark.parametrize("off", [-0.2, -0.05, 0.05, 0.2])
def test_true_lag_outside_the_declared_interval_measured(robot, dumbbells, off):
    """Declared [0.1045, 0.1155] (±5 %), the true lag outside it by `off` (below lo / above hi):
    how many of 8 cases latch `consistent` off (detected) and how many publish a box without the
    truth marked consistent (not detected). Printed for docs/guarantees.md (A4)."""
    outside_draw = lambda rng, index, lo, hi: hi * (1 + off) if off > 0 else lo * (1 + off)  # noqa: E731
    cases = lag_interval_cases(robot, dumbbells, 0.05, outside_draw, 8)
    detected = sum(not r[-1][1] for _, _, r in cases)
    wrong = sum(any(b and not a for a, b, _ in r) for _, _, r in cases)
    print(f"\ntrue lag {off:+.0%} outside: {detected}/8 detected (consistent off), {wrong}/8 wrong box published")
    assert len(cases) == 8


def test_offline_lag_undo_encloses_every_lag_in_the_interval(robot, dumbbells):
    """`sysid --model`'s undo_torque_lag (the noise after the filter): over [lo, hi] each row's
    ∫τ moves to the midpoint's and its error term grows so that the row of every lag d in the
    interval (its ∫τ ± its own term) lies inside; one value is the old arithmetic, bit for bit."""
    import copy

    from safesysid.sysid_cli import undo_torque_lag

    t, q, v, tau_meas, *_ = make_case(robot, dumbbells, 2, duration_s=0.6)
    est = E.IncrementalEstimator(robot, settings=settings(0.0), prior=PRIOR, prior_nominal=PRIOR_NOMINAL)
    est.add(t, q, v, tau_meas)

    def undone(lag):
        rows = copy.deepcopy(est.rows)
        undo_torque_lag(rows, tau_meas, lag, settings=est.settings)
        return rows

    interval = undone([0.09, 0.13])
    for d in (0.09, 0.1, 0.11, 0.13):
        point = undone(d)
        reach = np.abs(point.T - interval.T) + point.quad - est.rows.quad
        assert np.all(reach <= (interval.quad - est.rows.quad) * (1 + 1e-9)), d  # up to the rounding of the sums
    same = undone([0.11, 0.11])
    assert np.array_equal(same.T, undone(0.11).T) and np.array_equal(same.quad, undone(0.11).quad)
