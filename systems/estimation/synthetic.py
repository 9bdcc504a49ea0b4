"""Synthetic joint logs (validation, benchmarks, Table V): smooth Fourier motions within the
joint limits, the held torque that produces them, bounded noise.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from .settings import EstimatorError

if TYPE_CHECKING:
    from safesysid.systems.model.robot_model import RobotModel

# motion(times) -> (q, v, a) at those times
Motion = Callable[[ArrayLike], tuple[np.ndarray, np.ndarray, np.ndarray]]


def fourier_motion(
    rng: np.random.Generator,
    robot: RobotModel,
    duration_s: float,
    rate_hz: float,
    *,
    harmonics: int = 5,
    period_s: float | None = None,
    centre: ArrayLike | None = None,
    velocity_fraction: float = 0.7,
    position_amplitude_rad: float = 0.6,
    t0: float = 0.0,
) -> tuple[np.ndarray, Motion]:
    """Smooth random finite Fourier series (Swevers form) within joint position/velocity limits.

    q_j(t) = c_j + Σ_l a_jl/(lω) sin(lωt) − b_jl/(lω) cos(lωt), scaled on the sample grid.
    Returns (t, motion): the grid and motion(times) -> (q, v, a) at any times.
    """
    n = robot.n
    jp = robot.joint_params
    period = period_s or max(duration_s, 1.0)
    w = 2 * np.pi / period
    t = t0 + np.arange(int(round(duration_s * rate_hz)) + 1) / rate_hz
    a_c = rng.uniform(-1, 1, (n, harmonics))
    b_c = rng.uniform(-1, 1, (n, harmonics))
    ell = np.arange(1, harmonics + 1)

    def series(times):
        wt = np.outer(times, ell * w)  # (N, L)
        sin, cos = np.sin(wt), np.cos(wt)
        q_dev = (sin @ (a_c / (ell * w)).T) - (cos @ (b_c / (ell * w)).T)
        v = cos @ a_c.T + sin @ b_c.T
        acc = -(sin * (ell * w)) @ a_c.T + (cos * (ell * w)) @ b_c.T
        return q_dev, v, acc

    q_dev, v, _ = series(t)
    mean = q_dev.mean(0)
    # Scale per joint: velocity within the fraction of the limit, deviation within the amplitude.
    s_v = velocity_fraction * jp.velocity_limit / np.maximum(np.abs(v).max(0), 1e-9)
    s_q = position_amplitude_rad / np.maximum(np.abs(q_dev - mean).max(0), 1e-9)
    s = np.minimum(s_v, s_q)
    if centre is None:
        centre = np.zeros(n)
        finite = np.isfinite(jp.position_lower) & np.isfinite(jp.position_upper)
        centre[finite] = 0.5 * (jp.position_lower + jp.position_upper)[finite]
    centre = np.asarray(centre, float)

    def motion(times):
        q_dev, v, acc = series(np.atleast_1d(np.asarray(times, float)))
        return centre + (q_dev - mean) * s, v * s, acc * s

    q = motion(t)[0]
    if not (np.all(q >= jp.position_lower) and np.all(q <= jp.position_upper)):
        raise EstimatorError("trajectory leaves the joint limits; choose a centre inside them")
    return t, motion


def fourier_trajectory(
    rng: np.random.Generator, robot: RobotModel, duration_s: float, *, rate_hz: float, **kw: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`fourier_motion` sampled on its grid: t, q, v, a."""
    t, motion = fourier_motion(rng, robot, duration_s, rate_hz, **kw)
    return (t, *motion(t))


_GAUSS_NODES, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(3)


def held_torque(robot: RobotModel, motion: Motion, t: np.ndarray, *, theta: np.ndarray) -> np.ndarray:
    """The torque a zero-order hold must apply on each step [t_k, t_k+1] to produce `motion`
    exactly, in the momentum sense: τ̄_k = (1/h_k) ∫ τ_ID dt (3-point Gauss, error ~h⁶; the last sample
    holds over one more step of the same length). Over any segment of whole steps
    ∫ τ_ID dt = Σ τ̄_k h_k, so (t, q, v, τ̄) is an exact held-torque log of the motion."""
    h = np.diff(t)
    h = np.append(h, h[-1])
    nodes = t[:, None] + 0.5 * h[:, None] * (1 + _GAUSS_NODES[None, :])  # (N, 4)
    q, v, a = motion(nodes.ravel())
    tau = robot.inverse_dynamics(q, v, a, theta=theta).reshape(len(t), len(_GAUSS_NODES), -1)
    return 0.5 * np.tensordot(tau, _GAUSS_WEIGHTS, axes=([1], [0]))


def perturbed_robot_theta(rng: np.random.Generator, robot: RobotModel, ratio: float) -> np.ndarray:
    """Rest-of-robot θ_r perturbed uniformly within ±ratio·|θ_r| (what [θ_r] allows)."""
    theta = robot.theta.copy()
    mask = robot.rest_mask()
    theta[mask] *= 1 + rng.uniform(-ratio, ratio, mask.sum())
    return theta


def simulate_log(
    rng: np.random.Generator,
    robot: RobotModel,
    theta_true: np.ndarray,
    *,
    duration_s: float = 7.5,
    rate_hz: float = 1000.0,
    noise_ratio: float = 0.025,
    noise_floor_Nm: float = 0.05,
    noise_scale: float = 1.0,
    torque: str = "held",
    **traj: Any,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Joint log of an open-loop exciting motion with θ_true, plus uniform noise inside
    |τ_meas − τ| ≤ noise_scale·(ratio|τ| + floor). torque "held": τ is the zero-order-hold
    torque that produces the motion (`held_torque`, what a digital controller applies);
    "sampled": τ is inverse dynamics at the sample instants. Returns t, q, v, τ_meas, τ."""
    t, motion = fourier_motion(rng, robot, duration_s, rate_hz, **traj)
    q, v, a = motion(t)
    tau = (
        held_torque(robot, motion, t, theta=theta_true)
        if torque == "held"
        else robot.inverse_dynamics(q, v, a, theta=theta_true)
    )
    bound = noise_scale * (noise_ratio * np.abs(tau) + noise_floor_Nm)
    tau_meas = tau + rng.uniform(-1, 1, tau.shape) * bound
    return t, q, v, tau_meas, tau
