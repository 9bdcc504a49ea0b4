"""A5 (the quadrature of ∫W_c θ dt) checked where the motion between the samples is known
(`IncrementalEstimator.add(..., reference=motion)`, `segments.resolved_quadrature`): a joint
motion that oscillates between the samples (zero at every sample, so the samples are those of a
smooth motion) violates A5 while the samples' own quadrature term stays small; the check proves
it false, says so, and the sub-step bound keeps the truth inside. Without the reference the
estimate says A5 is unverified."""

import helpers
import numpy as np
import pytest
from helpers import CENTRE, PRIOR, PRIOR_NOMINAL
from safesysid.systems import estimation as E
from safesysid.systems.model.payload import payload_theta_in_end_effector

RATE_HZ = 1000.0


def oscillating(motion, amplitude_rad):
    """motion + amplitude·sin²(π t/h) on every joint: q and v unchanged at every sample t_k = k h."""
    w = np.pi * RATE_HZ

    def moved(times):
        q, v, a = motion(times)
        s = np.atleast_1d(times)[:, None]
        return (
            q + amplitude_rad * np.sin(w * s) ** 2,
            v + amplitude_rad * w * np.sin(2 * w * s),
            a + 2 * amplitude_rad * w**2 * np.cos(2 * w * s),
        )

    return moved


def held_torque(robot, motion, t, theta):
    return helpers.held_torque(robot, motion, t, theta, h=1.0 / RATE_HZ)


@pytest.fixture(scope="module")
def case(robot, dumbbells):
    rng = np.random.default_rng(5)
    theta = robot.theta.copy()
    theta[robot.ee_slice] = robot.theta_e + payload_theta_in_end_effector(dumbbells["8lb"], robot.extra["grasp_point"])
    t, smooth = E.fourier_motion(rng, robot, 2.0, RATE_HZ, centre=CENTRE)
    return t, smooth, oscillating(smooth, 2e-4), theta


def estimator(robot, t, motion, theta, reference):
    """An IncrementalEstimator fed the held-torque log of `motion` (noise-free) and its row residuals
    |Y θ_e + D_r θ_r − ∫τ|: with the torque exact, only the quadrature of ∫W_c θ dt errs."""
    q, v, _ = motion(t)
    est = E.IncrementalEstimator(
        robot, settings=E.EstimatorSettings(set_membership="none"), prior=PRIOR, prior_nominal=PRIOR_NOMINAL
    )
    est.add(t, q, v, held_torque(robot, motion, t, theta=theta), reference=reference)
    r = est.rows
    residual = np.abs(r.Y @ theta[robot.ee_slice] + r.D_r @ theta[robot.rest_mask()] - r.T)
    return est, residual


def test_oscillation_between_samples_is_caught_and_bounded(robot, case):
    """Unchecked, the samples' quadrature bound is exceeded on some row while its term stays
    below the warning (A5 silently false); checked, the estimator proves A5 false, every row's
    error is inside its re-derived bound, and the estimate says so and holds the truth."""
    t, _, moved, theta = case
    unchecked, residual = estimator(robot, t, moved, theta, None)
    ratio = np.max(unchecked.rows.quad / E.enclosure.torque_row_radius(unchecked.rows))
    print(f"\nunchecked: {np.max(residual / unchecked.rows.quad):.1f}× the quadrature bound, its ratio {ratio:.2f}")
    assert np.any(residual > unchecked.rows.quad) and ratio < 1.0
    checked, residual = estimator(robot, t, moved, theta, moved)
    assert checked.rows.a5_violated.any() and np.all(residual <= checked.rows.quad)
    e = checked.update()
    assert e.quadrature_assumption == "violated" and any("A5" in m for m in checked.messages)
    assert e.contains(theta[robot.ee_slice]) and e.consistent
    assert unchecked.update().quadrature_assumption == "unverified"


def test_a_smooth_motion_checks_without_false_alarm(robot, case):
    t, smooth, _, theta = case
    est, residual = estimator(robot, t, smooth, theta, smooth)
    assert est.rows.a5_checked.all() and not est.rows.a5_violated.any() and np.all(residual <= est.rows.quad)
    assert est.update().quadrature_assumption == "checked"
