import numpy as np
from safesysid.systems.math.bezier import QuinticBezier


def make(seed=0):
    rng = np.random.default_rng(seed)
    return QuinticBezier(rng.normal(size=7), rng.normal(size=7), rng.normal(size=7), 3.0), rng.normal(size=7)


def test_boundary_conditions_and_rest_at_the_end():
    b, q_end = make()
    q, qd, qdd = b.evaluate([0.0, 3.0, 3.5], q_end)
    assert np.allclose([q[0], qd[0], qdd[0]], [b.q0, b.v0, b.a0])
    assert np.allclose(q[1], q_end) and np.allclose(qd[1], 0) and np.allclose(qdd[1], 0)
    assert np.allclose(q[2], q_end) and np.allclose(qd[2], 0)


def test_derivatives_match_finite_differences():
    b, q_end = make(1)
    t = np.linspace(0.1, 2.9, 50)
    h = 1e-5
    q_p, qd_p, _ = b.evaluate(t + h, q_end)
    q_m, qd_m, _ = b.evaluate(t - h, q_end)
    _, qd, qdd = b.evaluate(t, q_end)
    assert np.allclose((q_p - q_m) / (2 * h), qd, atol=1e-6)
    assert np.allclose((qd_p - qd_m) / (2 * h), qdd, atol=1e-5)


def test_interval_bounds_contain_the_continuous_curve():
    for seed in range(5):
        b, q_end = make(seed)
        edges = np.linspace(0, 3, 33)
        bounds = b.interval_bounds(q_end, edges)
        t = np.linspace(0, 3, 20001)
        idx = np.minimum(np.searchsorted(edges, t, side="right") - 1, 31)
        for (lo, hi), x in zip(bounds, b.evaluate(t, q_end)):
            assert np.all(x >= lo[idx] - 1e-12) and np.all(x <= hi[idx] + 1e-12)


def test_end_weights_are_the_gradient_in_q_end():
    b, q_end = make(2)
    t = np.linspace(0, 3, 7)
    dq = np.zeros(7)
    dq[3] = 1e-6
    for w, x_p, x_0 in zip(QuinticBezier.end_weights(t, 3.0), b.evaluate(t, q_end + dq), b.evaluate(t, q_end)):
        assert np.allclose((x_p - x_0)[:, 3] / 1e-6, w, atol=1e-6)
