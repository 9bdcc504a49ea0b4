"""The classical exciting trajectory of "grav-pid-excit" (paper §VII-B, its ref. [7]: Swevers et al.,
a finite Fourier series optimized for the condition number of the regressor), constrained ONLY in
joint velocity and acceleration, as the paper says: no position limits, no collision, no torque
(that is the point of the comparison). Pure math, no LeafSystem.

Per joint i, base pulsation w = 2 pi / T and harmonics l = 1..L:
    qd_i(t)  = sum_l a_il cos(w l t) + b_il sin(w l t)
    q_i(t)   = q0_i + sum_l [a_il sin(w l t) + b_il (1 - cos(w l t))] / (w l)
    qdd_i(t) = sum_l w l (b_il cos(w l t) - a_il sin(w l t))
so q(0) = q0 by construction; rest at t = 0 (and, the series being T-periodic, at t = T, back at q0)
needs sum_l a_il = 0 (velocity) and sum_l l b_il = 0 (acceleration): a_i1 and b_i1 are eliminated.
After one period the trajectory holds q0.

Bounds, exact in continuous time (|a cos x + b sin x| <= sqrt(a^2 + b^2)):
    |qd_i(t)| <= sum_l r_il <= v_max_i,   |qdd_i(t)| <= w sum_l l r_il <= a_max_i,   r_il = |(a_il, b_il)|.
Cost: log of the 2-norm condition number of the stacked end-effector regressor W_e at
`num_cost_samples` instants of one period (the same excitation measure as the planner), exact
gradient by complex step; scipy SLSQP from a seeded random start that meets the bounds.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.model.robot_defaults import robot_defaults

if TYPE_CHECKING:
    from safesysid.systems.config import Scenario
    from safesysid.systems.model.robot_model import RobotModel

# Smooths r_il = sqrt(a^2 + b^2 + eps^2) at 0 for the solver; it only over-estimates r_il, so the
# constraint stays sufficient.
_EPS = 1e-9
_COMPLEX_STEP = 1e-30


@dataclass(frozen=True)
class FourierTrajectory:
    q0: np.ndarray  # (n,) start and end configuration [rad]
    a: np.ndarray  # (n, L) cosine coefficients of qd [rad/s]
    b: np.ndarray  # (n, L) sine coefficients of qd [rad/s]
    period_s: float

    @property
    def omega(self) -> float:
        return 2.0 * np.pi / self.period_s

    @property
    def duration(self) -> float:
        return self.period_s

    def evaluate(self, t: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, qd, qdd), each (len(t), n) for an array t, (n,) for a scalar; at rest at q0
        outside [0, T]."""
        scalar = np.ndim(t) == 0
        t = np.atleast_1d(np.asarray(t, float))
        inside = (t >= 0.0) & (t <= self.period_s)
        gq, gv, ga = basis(np.where(inside, t, 0.0), self.omega, self.a.shape[1])
        coef = np.concatenate([self.a, self.b], 1).T  # (2L, n)
        q, v, a = self.q0 + gq @ coef, gv @ coef, ga @ coef
        v[~inside], a[~inside] = 0.0, 0.0
        q[~inside] = self.q0
        return (q[0], v[0], a[0]) if scalar else (q, v, a)

    def velocity_bound(self) -> np.ndarray:
        """(n,) continuous-time bound on |qd_i|."""
        return np.hypot(self.a, self.b).sum(1)

    def acceleration_bound(self) -> np.ndarray:
        """(n,) continuous-time bound on |qdd_i|."""
        harmonics = np.arange(1, self.a.shape[1] + 1)
        return self.omega * (np.hypot(self.a, self.b) * harmonics).sum(1)


def basis(t: ArrayLike, omega: float, num_harmonics: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(G_q, G_v, G_a), each (len(t), 2L): q - q0, qd, qdd = G [a_1..a_L, b_1..b_L] per joint."""
    wl = omega * np.arange(1, num_harmonics + 1)
    x = np.outer(np.asarray(t, float), wl)
    s, c = np.sin(x), np.cos(x)
    gq = np.concatenate([s / wl, (1.0 - c) / wl], 1)
    gv = np.concatenate([c, s], 1)
    ga = np.concatenate([-wl * s, wl * c], 1)
    return gq, gv, ga


def elimination(num_harmonics: int) -> np.ndarray:
    """E (2L, 2L - 2): [a; b] = E [a_2..a_L, b_2..b_L] with sum a_l = 0 and sum l b_l = 0."""
    L = num_harmonics
    free = L - 1
    E = np.zeros((2 * L, 2 * free))
    E[1:L, :free] = np.eye(free)
    E[L + 1 :, free:] = np.eye(free)
    E[0, :free] = -1.0
    E[L, free:] = -np.arange(2, L + 1)
    return E


@dataclass(frozen=True)
class FourierSettings:
    period_s: float
    num_harmonics: int
    velocity_limit: np.ndarray  # (n,) rad/s
    acceleration_limit: np.ndarray  # (n,) rad/s^2
    num_cost_samples: int
    max_iterations: int
    seed: int


@dataclass(frozen=True)
class FourierResult:
    trajectory: FourierTrajectory
    cond: float  # condition number of the stacked W_e at the cost samples
    initial_cond: float
    iterations: int
    status: str
    solve_time_s: float


class _Problem:
    """The exciting cost and the bound constraints on the free coefficients x (n, 2L - 2)."""

    def __init__(self, robot: RobotModel, q0: ArrayLike, settings: FourierSettings) -> None:
        self.robot, self.s = robot, settings
        self.q0 = np.asarray(q0, float)
        self.n, self.L = robot.n, settings.num_harmonics
        self.E = elimination(self.L)
        self.omega = 2.0 * np.pi / settings.period_s
        t = np.arange(settings.num_cost_samples) * settings.period_s / settings.num_cost_samples
        self.G = [g @ self.E for g in basis(t, self.omega, self.L)]  # each (T, 2L - 2)

    def full(self, x) -> tuple[np.ndarray, np.ndarray]:
        coef = x.reshape(self.n, -1) @ self.E.T  # (n, 2L)
        return coef[:, : self.L], coef[:, self.L :]

    def cost(self, x) -> tuple[float, np.ndarray]:
        """log sigma_max - log sigma_min of W_e and its exact gradient in x. The rows of sample t
        depend on (q, qd, qdd)(t) only, so one complex-step copy per (joint, derivative order)
        perturbing every sample at once gives each sample's partials (3 n copies)."""
        from safesysid.systems.planner.ee_regressor import ee_standard_regressor

        n = self.n
        X = x.reshape(n, -1)
        base = [g @ X.T for g in self.G]  # q - q0, qd, qdd: (T, n) each
        base[0] = base[0] + self.q0
        T = base[0].shape[0]
        pert = np.zeros((3, n, 3, T, n), complex)  # [order, joint] copies of (q, qd, qdd)
        pert[...] = np.stack(base)[None, None]
        for k in range(3):
            for j in range(n):
                pert[k, j, k, :, j] += 1j * _COMPLEX_STEP
        samples = pert.reshape(3 * n, 3, T, n)
        w = ee_standard_regressor(
            self.robot.tree,
            self.robot.end_effector,
            samples[:, 0].reshape(-1, n),
            v=samples[:, 1].reshape(-1, n),
            a=samples[:, 2].reshape(-1, n),
        ).reshape(3 * n, T, n, 10)
        W = w[0].real.reshape(T * n, 10)
        dW = (w.imag / _COMPLEX_STEP).reshape(3, n, T, n, 10)  # [order, joint, t, row, col]
        u, sv, vt = np.linalg.svd(W, full_matrices=False)
        if sv[-1] <= 0:
            return np.inf, np.zeros_like(x)
        u_max, u_min = u[:, 0].reshape(T, n), u[:, -1].reshape(T, n)
        sens = np.einsum("tr,kjtrc,c->ktj", u_max, dW, vt[0]) / sv[0]
        sens -= np.einsum("tr,kjtrc,c->ktj", u_min, dW, vt[-1]) / sv[-1]
        grad = sum(self.G[k].T @ sens[k] for k in range(3))  # (2L - 2, n)
        return float(np.log(sv[0] / sv[-1])), grad.T.ravel()

    def slack(self, x) -> tuple[np.ndarray, np.ndarray]:
        """Constraint values (>= 0 feasible): [v_max - bound_v, a_max - bound_a] (2 n,) and Jacobian."""
        a, b = self.full(x)
        r = np.sqrt(a * a + b * b + _EPS**2)
        harm = np.arange(1, self.L + 1)
        values = np.concatenate(
            [self.s.velocity_limit - r.sum(1), self.s.acceleration_limit - self.omega * (r * harm).sum(1)]
        )
        # d r_il / d [a; b]_il, then through E to the free variables of joint i.
        dr = np.concatenate([a / r, b / r], 1)  # (n, 2L)
        jac = np.zeros((2 * self.n, self.n, self.E.shape[1]))
        weights = [np.ones(self.L), self.omega * harm]
        for k, wgt in enumerate(weights):
            full_w = np.concatenate([wgt, wgt])  # the same r_il for a_il and b_il
            jac[k * self.n + np.arange(self.n), np.arange(self.n)] = -(dr * full_w) @ self.E
        return values, jac.reshape(2 * self.n, -1)

    def project(self, x) -> np.ndarray:
        """x with each joint's coefficients scaled down until its two bounds hold (scaling keeps
        the rest conditions, and both bounds are linear in the scale)."""
        a, b = self.full(x)
        r = np.hypot(a, b)
        harm = np.arange(1, self.L + 1)
        with np.errstate(divide="ignore"):
            scale = np.minimum(
                self.s.velocity_limit / r.sum(1), self.s.acceleration_limit / (self.omega * (r * harm).sum(1))
            )
        # The solver's smoothing (_EPS) makes its bound a hair larger: shrink by the same margin.
        scale = np.minimum(1.0, scale * (1.0 - 1e-9))
        return (x.reshape(self.n, -1) * scale[:, None]).ravel()

    def start(self, rng) -> np.ndarray:
        """Random free coefficients scaled to use half of the tighter bound of each joint."""
        x = rng.uniform(-1.0, 1.0, (self.n, self.E.shape[1]))
        a, b = self.full(x.ravel())
        r = np.hypot(a, b)
        harm = np.arange(1, self.L + 1)
        scale = 0.5 * np.minimum(
            self.s.velocity_limit / r.sum(1), self.s.acceleration_limit / (self.omega * (r * harm).sum(1))
        )
        return (x * scale[:, None]).ravel()


def optimize_fourier(robot: RobotModel, q0: ArrayLike, settings: FourierSettings) -> FourierResult:
    """The most exciting Fourier trajectory (min cond W_e) from rest at q0 back to rest at q0,
    inside the velocity and acceleration limits only. SLSQP's iterates may sit slightly outside the
    bounds: each is projected inside (Problem.project) and the best projected one is kept (the
    seeded start is inside by construction), whatever the solver's final status."""
    from scipy.optimize import minimize

    prob = _Problem(robot, q0, settings)
    x0 = prob.start(np.random.default_rng(settings.seed))
    best = {"x": x0, "cost": prob.cost(x0)[0]}
    initial = best["cost"]

    def keep_if_better(x):
        inside = prob.project(x)
        value = prob.cost(inside)[0]
        if value < best["cost"]:
            best.update(x=inside, cost=value)

    wall = time.perf_counter()
    res = minimize(
        prob.cost,
        x0,
        jac=True,
        method="SLSQP",
        constraints=[{"type": "ineq", "fun": lambda x: prob.slack(x)[0], "jac": lambda x: prob.slack(x)[1]}],
        options={"maxiter": settings.max_iterations, "ftol": 1e-6},
        callback=keep_if_better,
    )
    keep_if_better(res.x)
    wall = time.perf_counter() - wall
    a, b = prob.full(best["x"])
    traj = FourierTrajectory(prob.q0.copy(), a, b, float(settings.period_s))
    cond, cond0 = float(np.exp(best["cost"])), float(np.exp(initial))
    return FourierResult(traj, cond, cond0, int(res.nit), str(res.message), wall)


def fourier_settings(robot: RobotModel, scenario: Scenario) -> FourierSettings:
    from safesysid.systems.excitation.fourier import FourierSettings

    f = scenario.fourier
    key = "fourier.acceleration_limit_rad_s2"
    acceleration = (
        f.acceleration_limit_rad_s2 if np.size(f.acceleration_limit_rad_s2) else robot_defaults(robot, [key])[key]
    )  # unset: the robot's
    return FourierSettings(
        period_s=float(f.period_s),
        num_harmonics=int(f.num_harmonics),
        velocity_limit=np.asarray(robot.joint_params.velocity_limit, float),
        acceleration_limit=np.asarray(acceleration, float),
        num_cost_samples=int(f.num_cost_samples),
        max_iterations=int(f.max_iterations),
        seed=int(scenario.seed),
    )


_FOURIER_CACHE: dict = {}  # (id(robot), q0, settings) -> (robot, FourierResult); the robot kept alive


def fourier_excitation(robot: RobotModel, scenario: Scenario) -> FourierResult:
    """The grav-pid-excit trajectory of a scenario (FourierResult), optimized once per process
    and robot model."""
    from safesysid.systems.excitation.fourier import optimize_fourier

    s = fourier_settings(robot, scenario)
    q0 = np.asarray(scenario.q0_rad, float)
    arrays = (q0, s.velocity_limit, s.acceleration_limit)
    key = (id(robot), *(a.tobytes() for a in arrays), s.period_s, s.num_harmonics, s.num_cost_samples)
    key += (s.max_iterations, s.seed)
    if key not in _FOURIER_CACHE:
        _FOURIER_CACHE[key] = (robot, optimize_fourier(robot, q0, s))
    return _FOURIER_CACHE[key][1]
