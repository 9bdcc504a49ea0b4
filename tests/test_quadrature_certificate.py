"""A5 certified from an acceleration bound (estimation/quadrature_certificate.py,
`segments.certified_rows`): a joint motion whose velocity oscillates between the samples (zero
at every sample, so the samples are those of a smooth motion) with its acceleration under the
declared bound breaks A5's bound while its term stays below the warning; with the bound the
estimator says A5 is not shown ("certified"), every row holds its error and the box the truth.
A bound the samples contradict latches `consistent` off. Printed with -s."""

import helpers
import numpy as np
import pytest
from helpers import CENTRE, PRIOR, PRIOR_NOMINAL
from safesysid.systems import estimation as E
from safesysid.systems.estimation import quadrature_certificate as qc
from safesysid.systems.math.intervals import Interval
from safesysid.systems.model.payload import payload_theta_in_end_effector

RATE_HZ = 1000.0
H = 1.0 / RATE_HZ
GAUSS = helpers.GAUSS


def wobbling(motion, speed_rad_s):
    """motion + a velocity speed·sin(2π t/h) on every joint: q, q̇ unchanged at every sample."""
    w = 2 * np.pi * RATE_HZ

    def moved(times):
        q, v, a = motion(times)
        s = np.atleast_1d(times)[:, None]
        return (
            q + speed_rad_s / w * (1 - np.cos(w * s)),
            v + speed_rad_s * np.sin(w * s),
            a + speed_rad_s * w * np.cos(w * s),
        )

    return moved


def acceleration_bound(motion, t):
    """Per joint, above max |q̈| of the motion (dense samples, 10 % margin: the test's input)."""
    _, _, a = motion(np.linspace(t[0], t[-1], 64 * len(t)))
    return 1.1 * np.abs(a).max(0) + 1e-3


def held_torque(robot, motion, t, theta):
    return helpers.held_torque(robot, motion, t, theta, h=H)


@pytest.fixture(scope="module")
def case(robot, dumbbells):
    rng = np.random.default_rng(5)
    theta = robot.theta.copy()
    theta[robot.ee_slice] = robot.theta_e + payload_theta_in_end_effector(dumbbells["8lb"], robot.extra["grasp_point"])
    t, smooth = E.fourier_motion(rng, robot, 1.0, RATE_HZ, centre=CENTRE)
    moved = wobbling(smooth, 0.05)
    logs = {name: (m, held_torque(robot, m, t, theta)) for name, m in (("smooth", smooth), ("moved", moved))}
    return t, logs, theta


def estimator(robot, t, log, theta, bound):
    """The estimator fed the exact held-torque log (motion, torque), and each row's true error
    |Y θ_e + D_r θ_r − ∫τ| (the quadrature's alone)."""
    motion, tau = log
    q, v, _ = motion(t)
    est = E.IncrementalEstimator(
        robot, settings=E.EstimatorSettings(set_membership="none"), prior=PRIOR, prior_nominal=PRIOR_NOMINAL
    )
    est.add(t, q, v, tau, acceleration_bound=bound)
    r = est.rows
    return est, np.abs(r.Y @ theta[robot.ee_slice] + r.D_r @ theta[robot.rest_mask()] - r.T)


def test_the_interval_rate_regressor_holds_every_state_of_its_boxes(robot):
    rng = np.random.default_rng(0)
    q0, v0 = rng.uniform(-2, 2, (40, robot.n)), rng.uniform(-1, 1, (40, robot.n))
    box = qc.interval_rate_regressor(robot, Interval(q0 - 1e-3, q0 + 1e-3), Interval(v0 - 1e-2, v0 + 1e-2))
    for _ in range(10):
        q, v = q0 + rng.uniform(-1e-3, 1e-3, q0.shape), v0 + rng.uniform(-1e-2, 1e-2, v0.shape)
        assert np.all(box.contains(qc.point_rate_regressor(robot, q, v)))


def test_the_step_boxes_hold_the_motion_and_the_certificate_its_error(robot, case):
    """Per step (the first 100 of the oscillating log): every dense state in its sub-step's box,
    and the certificate above the step's true quadrature error (24-point Gauss)."""
    t, logs, theta = case
    motion, t = logs["moved"][0], t[:101]
    q, v, _ = motion(t)
    bound = acceleration_bound(motion, t)
    qb, vb, bad = qc.step_boxes(t, q, v, np.broadcast_to(bound, (100, robot.n)), 4)
    dense = t[:-1, None] + H * np.linspace(0, 1, 33)[None, :]
    dq, dv, _ = motion(dense.ravel())
    sub = np.minimum((np.linspace(0, 1, 33) * 4).astype(int), 3)  # the sub-step each instant is in
    for box, x in ((qb, dq), (vb, dv)):
        inside = box[:, sub].contains(x.reshape(100, 33, -1))
        assert not bad.any() and inside.all()
    cert, _ = qc.certified_step_bounds(
        robot, t, q, v, np.broadcast_to(bound, (100, robot.n)), (theta, 0 * theta), integration="trapezoid"
    )
    nodes = t[:-1, None] + 0.5 * H * (1 + GAUSS[0][None, :])
    f = qc.point_rate_regressor(robot, *motion(nodes.ravel())[:2]) @ theta
    exact = 0.5 * H * np.tensordot(f.reshape(100, len(GAUSS[0]), -1), GAUSS[1], axes=([1], [0]))
    fs = qc.point_rate_regressor(robot, q, v) @ theta
    error = np.abs(exact - 0.5 * H * (fs[:-1] + fs[1:]))
    print(f"\nper step: error at most {np.max(error / cert):.3f} of the certificate")
    assert np.all(error <= cert)


def test_an_oscillation_between_samples_under_the_bound_is_certified_not_assumed(robot, case):
    t, logs, theta = case
    moved = logs["moved"]
    bound = acceleration_bound(moved[0], t)
    plain, residual = estimator(robot, t, moved, theta, None)
    ratio = np.max(plain.rows.quad / E.enclosure.torque_row_radius(plain.rows))
    print(f"\nA5 alone: {np.max(residual / plain.rows.quad):.1f}× its bound, term {ratio:.2f} of the torque radius")
    assert np.any(residual > plain.rows.quad) and ratio < 1.0  # A5 false, and nothing says so
    assert plain.update().quadrature_assumption == "unverified"
    est, residual = estimator(robot, t, moved, theta, bound)
    print(f"certified: the error at most {np.max(residual / est.rows.quad):.3f} of the row's term")
    assert est.rows.a5_certified.all() and not est.rows.a5_shown.all() and np.all(residual <= est.rows.quad)
    e = est.update()
    assert e.quadrature_assumption == "certified" and any("A5" in m for m in est.messages)
    assert e.consistent and e.contains(theta[robot.ee_slice])


def test_a_smooth_motion_is_certified_without_false_alarm_and_a_contradicted_bound_latches(robot, case):
    t, logs, theta = case
    smooth = logs["smooth"]
    bound = acceleration_bound(smooth[0], t)
    est, residual = estimator(robot, t, smooth, theta, bound)
    plain, _ = estimator(robot, t, smooth, theta, None)
    grow = np.sum(est.rows.quad) / np.sum(plain.rows.quad)
    print(f"\nsmooth: {est.rows.a5_shown.mean():.2f} of the segments A5-shown, quadrature term {grow:.2f}× A5's")
    assert est.rows.a5_certified.all() and np.all(residual <= est.rows.quad)
    e = est.update()
    assert e.quadrature_assumption in ("checked", "certified") and e.consistent and e.contains(theta[robot.ee_slice])
    low, _ = estimator(robot, t, smooth, theta, 0.2 * bound)  # the samples' own mean accelerations exceed it
    assert low.rows.accel_violated.any() and not low.update().consistent


def test_a_closed_loop_run_with_a_declared_bound_is_certified_without_false_alarm(tmp_path):
    """The quickstart's first plan (3 s) with estimator.acceleration_bound_rad_s2 [0.5] (5× the
    run's peak mean acceleration): summary.json says certified, consistent, the truth inside."""
    import json

    from safesysid.cli import main
    from safesysid.scenario import SCENARIOS_DIR

    text = "planner: {num_plans: 1}\nestimator: {acceleration_bound_rad_s2: [0.5]}"
    assert main(["run", str(SCENARIOS_DIR / "quickstart.yaml"), "--out", str(tmp_path), "--scenario-text", text]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["estimate"]["quadrature_assumption"] == "certified"
    assert summary["estimate"]["consistent"] and summary["contains_truth"]
