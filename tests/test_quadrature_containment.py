"""Containment where the quadrature term (A5) matters.

The randomized and adversarial containment tests log smooth motions at 1 kHz under the default
declared noise: there the bound on the quadrature of ∫W_c θ dt stays near a tenth of the torque
radius, and removing it changes nothing they can see. Here a precise sensor (declared noise
0.2 % + 4 mN·m) and an almost exactly known rest of the robot (θ_r ± 0.01 %) log a fast motion
(1 s period, 70 % of the velocity limits) at 50 Hz: the quadrature term is many times the torque
radius, and the estimator must carry it. Without it every case is declared inconsistent although
every assumption holds (the true θ fits no row within its bound: the polytope is empty).
"""

import numpy as np
import pytest
from helpers import CENTRE, PAYLOADS, PRIOR, PRIOR_NOMINAL
from safesysid.systems import estimation as E
from safesysid.systems.config import ParameterFloors
from safesysid.systems.estimation import segments
from safesysid.systems.model.payload import payload_theta_in_end_effector
from safesysid.systems.model.torque_noise import DeclaredTorqueNoise

RATE_HZ = 50.0
SETTINGS = dict(
    hold_period_s=1 / RATE_HZ,
    declared_noise=DeclaredTorqueNoise(ratio=0.002, floor_Nm=0.004),
    theta_r_ratio=1e-4,
    theta_r_floor=ParameterFloors(*([1e-6] * 7)),
)
CASES = range(4)


def estimate(robot, dumbbells, index):
    """(estimate, θ_e true) of a 3 s held-torque log at 50 Hz, noise AT the declared bound (random
    signs), θ_r drawn in its box."""
    rng = np.random.default_rng(9100 + index)
    payload = dumbbells[PAYLOADS[index % len(PAYLOADS)]]
    theta_e = robot.theta_e + payload_theta_in_end_effector(payload, robot.extra["grasp_point"])
    t, motion = E.fourier_motion(rng, robot, 3.0, RATE_HZ, period_s=1.0, centre=CENTRE)
    q, v, _ = motion(t)
    settings = E.EstimatorSettings(**SETTINGS)
    est = E.IncrementalEstimator(robot, prior=PRIOR, prior_nominal=PRIOR_NOMINAL, settings=settings)
    theta = robot.theta.copy()
    theta[robot.ee_slice] = theta_e
    rest = robot.rest_mask()
    theta[rest] = est.theta_r + est.theta_r_radius * rng.uniform(-1, 1, rest.sum())
    tau = E.held_torque(robot, motion, t, theta=theta)
    tau_meas = tau + rng.choice([-1.0, 1.0], tau.shape) * (
        settings.declared_noise.ratio * np.abs(tau) + settings.declared_noise.floor_Nm
    )
    est.add(t, q, v, tau_meas)
    return est.update(), theta_e


def test_the_quadrature_term_keeps_the_truth_inside_where_it_dominates(robot, dumbbells):
    for index in CASES:
        e, theta_e = estimate(robot, dumbbells, index)
        print(index, e.consistent, e.contains(theta_e), e.quadrature_ratio)
        assert e.quadrature_ratio > 5.0  # the term is several torque radii: it matters here
        assert e.consistent and e.contains(theta_e), f"case {index}"
        assert np.any(e.upper - e.lower < PRIOR[1] - PRIOR[0])  # the data did narrow the prior


def test_without_the_quadrature_term_every_case_is_a_false_alarm(robot, dumbbells):
    """The power of the test above: with the term set to 0 the truth's own rows violate their bounds."""
    bound = segments.quadrature_bound
    mp = pytest.MonkeyPatch()
    mp.setattr(segments, "quadrature_bound", lambda *args, **kw: 0.0 * bound(*args, **kw))
    try:
        consistent = [estimate(robot, dumbbells, index)[0].consistent for index in CASES]
    finally:
        mp.undo()
    assert not any(consistent)


def test_the_bound_is_attained_by_an_integrand_monotone_on_each_step():
    """The trapezoid bound ¼κh²·max(a) with κ = 2 is tight: an integrand that rises by Δ in the first
    1e-6 of every step (monotone there, mean rate a = Δ/h) errs by hΔ/2 (1 − 1e-6) per step, the
    bound's hΔ/2. A κ below 2 would not cover it."""
    h, steps, delta, ramp = 0.01, 50, 0.3, 1e-6
    t = h * np.arange(steps + 1)
    f = delta * np.arange(steps + 1)  # the samples: +Δ per step
    exact = np.sum(h * f[:-1] + delta * h * (1 - ramp / 2))  # f_k + Δ on each step but its first ramp·h
    trapezoid = np.sum(0.5 * h * (f[:-1] + f[1:]))
    rates = np.full((steps, 1), delta / h)
    bound = segments.quadrature_bound(t, rates, np.array([[0, steps]]), integration="trapezoid", safety=2.0)[0, 0]
    error = abs(exact - trapezoid)
    assert error <= bound and error > 0.99 * bound
