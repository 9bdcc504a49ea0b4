"""The nonlinear least squares in log-Cholesky coordinates (θ0 = P(η*), physically consistent
by construction): cost, exact gradient and Hessian, the NLP and its trust-region polish.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from safesysid.systems.model import inertial


def ls_cost_terms(Y: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """A = YᵀY, b = YᵀU, c = UᵀU so that ‖Yθ − U‖² = θᵀAθ − 2bᵀθ + c."""
    return Y.T @ Y, Y.T @ U, float(U @ U)


def _centred(A, b, c):
    """θ_c = A⁻¹b and J_min, so that ½(θᵀAθ − 2bᵀθ + c) = ½(θ−θ_c)ᵀA(θ−θ_c) + J_min: the
    centred form keeps the cost accurate near the optimum (no cancellation of large terms)."""
    theta_c = np.linalg.solve(A, b)
    return theta_c, 0.5 * max(c - b @ theta_c, 0.0)


def cost_grad_hess(
    eta: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    c: float,
    *,
    centred: tuple[np.ndarray, float] | None = None,
) -> tuple[float, np.ndarray, np.ndarray]:
    """J(η) = ½‖Y P(η) − U‖² and its exact gradient and Hessian (paper appendix, eq. D_ee)."""
    theta_c, jmin = centred or _centred(A, b, c)
    theta = inertial.log_cholesky_to_theta(eta)
    jac = inertial.log_cholesky_jacobian(eta)
    d = theta - theta_c
    r = A @ d  # = Yᵀ(Yθ − U)
    J = 0.5 * d @ r + jmin
    g = jac.T @ r
    H = jac.T @ A @ jac + np.einsum("i,ikl->kl", r, inertial.log_cholesky_hessian(eta))
    return J, g, H


@dataclass
class SolveResult:
    eta: np.ndarray
    theta: np.ndarray
    cost: float
    grad_norm: float
    solver: str
    success: bool
    message: str = ""
    newton_steps: int = 0


_THETA_OF_J = np.stack([inertial.theta_from_pseudo_inertia(e.reshape(4, 4)) for e in np.eye(16)], 1)  # θ = L vec(J)
_OFFDIAG = [(0, 1), (0, 2), (1, 2), (0, 3), (1, 3), (2, 3)]  # η[4:] order of inertial.py
_OFF_R = np.array([rc[0] for rc in _OFFDIAG])
_OFF_C = np.array([rc[1] for rc in _OFFDIAG])


def cost_and_gradient(
    eta: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    c: float,
    *,
    centred: tuple[np.ndarray, float] | None = None,
) -> tuple[float, np.ndarray]:
    """J(η) and its exact gradient, the fast path used inside the NLP (≈ 20 µs)."""
    theta_c, jmin = centred or _centred(A, b, c)
    a = np.exp(eta[0])
    u = np.zeros((4, 4))
    u[[0, 1, 2], [0, 1, 2]] = np.exp(eta[1:4])
    u[3, 3] = 1.0
    u[_OFF_R, _OFF_C] = eta[4:]
    u *= a
    theta = _THETA_OF_J @ (u @ u.T).ravel()
    d = theta - theta_c
    r = A @ d
    J = 0.5 * d @ r + jmin
    rm = (_THETA_OF_J.T @ r).reshape(4, 4)
    G = (rm + rm.T) @ u  # dJ/dU
    g = np.empty(10)
    g[0] = np.sum(G * u)
    g[1:4] = np.diag(G)[:3] * np.diag(u)[:3]
    g[4:] = G[_OFF_R, _OFF_C] * a
    return J, g


ETA_LOWER = np.array([-20.0, -20, -20, -20] + [-1e4] * 6)
ETA_UPPER = np.array([20.0, 20, 20, 20] + [1e4] * 6)


def _solver(name):
    from pydrake.solvers import IpoptSolver, SnoptSolver

    if name == "snopt":
        s = SnoptSolver()
        if s.available() and s.enabled():
            return s, "snopt"
        return IpoptSolver(), "ipopt (snopt unavailable)"
    return IpoptSolver(), "ipopt"


def solve_log_cholesky(
    A: np.ndarray,
    b: np.ndarray,
    c: float,
    eta0: np.ndarray,
    *,
    solver: str = "ipopt",
    newton_steps: int = 50,
    scale: float | None = None,
    max_iterations: int = 20,
    max_time_s: float | None = None,
) -> SolveResult:
    """min_η ½‖Y P(η) − U‖² with Drake MathematicalProgram.

    The cost is a Python function evaluated on AutoDiffXd that returns the EXACT gradient
    (chain rule through dP/dη, no forward-mode over the data). Drake's Ipopt interface does not
    expose an exact Hessian callback (its eval_h is not implemented: Ipopt runs with a
    limited-memory quasi-Newton Hessian, and "hessian_approximation exact" aborts), so the answer
    is then polished by a trust-region Newton method on the exact Hessian (`cost_grad_hess`),
    kept only if it lowers the cost. Ipopt is capped in iterations (a time cap, max_time_s, only if
    asked: it makes the answer depend on machine load): L-BFGS is slow on this badly scaled map,
    and the exact-Hessian polish converges in a few steps from its answer. When the unconstrained
    optimum is not physically consistent the infimum sits on the LMI boundary and is not attained
    in η: the solvers then stop at an iterate close to it (reported, not an error).
    """
    from pydrake.autodiffutils import AutoDiffXd, ExtractGradient, ExtractValue

    # Cost scaling: Ipopt's tolerances are absolute; scale so the start costs O(1).
    # (Cost scaled by trace(A): the scaled Hessian in θ has eigenvalues ≤ 1.)
    scale = scale or max(np.trace(A), 1e-300)
    centred = _centred(A, b, c)

    def cost(x):
        if x.dtype == object:
            J, g = cost_and_gradient(ExtractValue(x).ravel(), A, b, c, centred=centred)
            return AutoDiffXd(J / scale, (g / scale) @ ExtractGradient(x))
        return cost_and_gradient(np.asarray(x, float), A, b, c, centred=centred)[0] / scale

    eta0 = np.clip(eta0, ETA_LOWER, ETA_UPPER)
    eta, ok, msg, name = _solve_nlp(cost, eta0, solver=solver, max_iterations=max_iterations, max_time_s=max_time_s)
    if not np.all(np.isfinite(eta)):
        eta = np.asarray(eta0, float)
    J = cost_and_gradient(eta, A, b, c, centred=centred)[0]
    eta, J, steps, polished = _newton_polish(eta, J, (A, b, c, centred), scale=scale, newton_steps=newton_steps)
    g = cost_and_gradient(eta, A, b, c, centred=centred)[1]
    # Stationary to working precision (relative to the curvature scale) counts as solved.
    ok = ok or polished or bool(np.linalg.norm(g) <= 1e-9 * scale * max(1.0, np.linalg.norm(eta)))
    return SolveResult(
        eta=eta,
        theta=inertial.log_cholesky_to_theta(eta),
        cost=J,
        grad_norm=float(np.linalg.norm(g)),
        solver=name,
        success=ok,
        message=msg,
        newton_steps=steps,
    )


def _solve_nlp(cost, eta0, *, solver, max_iterations, max_time_s):
    """(η, success, message, solver name) of Drake's NLP on `cost` inside the η box from eta0 (in
    the box); the start point when the solver crashes."""
    import logging

    from pydrake.solvers import MathematicalProgram, SolverOptions

    prog = MathematicalProgram()
    x = prog.NewContinuousVariables(10, "eta")
    prog.AddCost(cost, vars=x)
    # Keep η finite: when the unconstrained optimum is not physically consistent the infimum
    # lies on the LMI boundary (η → ∞); these bounds stop the search e^-20 away from it.
    prog.AddBoundingBoxConstraint(ETA_LOWER, ETA_UPPER, x)
    prog.SetInitialGuess(x, eta0)
    slv, name = _solver(solver)
    opts = SolverOptions()
    if name == "ipopt":
        opts.SetOption(slv.solver_id(), "print_level", 0)
        opts.SetOption(slv.solver_id(), "tol", 1e-9)
        # Warm start: a small barrier parameter and bound multipliers, so a start at the
        # optimum is accepted at iteration 0 instead of being pushed off by the barrier.
        opts.SetOption(slv.solver_id(), "mu_init", 1e-8)
        opts.SetOption(slv.solver_id(), "bound_mult_init_val", 1e-8)
        opts.SetOption(slv.solver_id(), "acceptable_tol", 1e-6)
        opts.SetOption(slv.solver_id(), "acceptable_iter", 3)
        opts.SetOption(slv.solver_id(), "max_iter", max_iterations)
        if max_time_s is not None:  # a CPU-time cap makes the estimate depend on machine load
            opts.SetOption(slv.solver_id(), "max_cpu_time", max_time_s)
    else:
        opts.SetOption(slv.solver_id(), "Major iterations limit", max_iterations)
    drake_log = logging.getLogger("drake")
    level = drake_log.level
    drake_log.setLevel(logging.ERROR)  # an iteration/time cap is expected near the LMI boundary
    try:
        res = slv.Solve(prog, eta0, opts)
        eta = np.asarray(res.GetSolution(x), float)
        ok = bool(res.is_success()) and np.all(np.isfinite(eta))
        msg = str(res.get_solution_result())
    except Exception as err:  # solver crash -> fall back to the start point, logged
        eta, ok, msg = np.asarray(eta0, float), False, f"solver error: {err}"
    finally:
        drake_log.setLevel(level)
    return eta, ok, msg, name


def _newton_polish(eta, J, data, *, scale, newton_steps):
    """Exact-Hessian polish: trust-region Newton (scipy trust-exact) on our exact gradient and
    Hessian, from the NLP's answer; kept only if it lowers the cost and stays in the η box.
    data = (A, b, c, centred). (η, cost, Newton steps taken, converged)."""
    A, b, c, centred = data
    steps = 0
    polished = False
    if newton_steps > 0:
        from scipy.optimize import minimize

        with np.errstate(over="ignore", invalid="ignore"):
            pol = minimize(
                lambda e: cost_and_gradient(e, A, b, c, centred=centred)[0] / scale,
                eta,
                jac=lambda e: cost_and_gradient(e, A, b, c, centred=centred)[1] / scale,
                hess=lambda e: cost_grad_hess(e, A, b, c, centred=centred)[2] / scale,
                method="trust-exact",
                options={"maxiter": newton_steps, "gtol": 1e-12},
            )
        if np.all(np.isfinite(pol.x)) and np.all(pol.x >= ETA_LOWER) and np.all(pol.x <= ETA_UPPER):
            Jp = cost_and_gradient(pol.x, A, b, c, centred=centred)[0]
            if np.isfinite(Jp) and Jp <= J:
                eta, J, steps = pol.x, Jp, int(pol.nit)
                polished = bool(pol.success)
    return eta, J, steps, polished


def ift_sensitivity(eta: np.ndarray, A: np.ndarray, b: np.ndarray, *, dU_dm_Y: np.ndarray) -> np.ndarray:
    """Paper appendix: ∂θ*/∂m = −P_η (∂²J/∂η²)⁻¹ ∂²J/∂m∂η at η, with dU_dm_Y = Yᵀ ∂U/∂m.

    At an interior least-squares optimum this equals Y⁺ ∂U/∂m (the residual-curvature term of
    the Hessian vanishes with the gradient); used by the tests to check that identity.
    """
    _, _, H = cost_grad_hess(eta, A, b, 0.0)
    jac = inertial.log_cholesky_jacobian(eta)
    mixed = -jac.T @ dU_dm_Y  # ∂²J/∂η∂m
    return -jac @ np.linalg.solve(H, mixed)


def nearest_consistent(theta: np.ndarray, rel_floor: float = 1e-6) -> np.ndarray:
    """θ whose pseudo-inertia is J(θ) with eigenvalues floored at rel_floor·λ_max (Frobenius
    projection onto the consistent set; equals θ when θ is already safely consistent)."""
    lam, vec = np.linalg.eigh(inertial.pseudo_inertia(theta))
    floor = rel_floor * max(lam.max(), 1e-9)
    if lam.min() > floor:
        return np.asarray(theta, float)
    return inertial.theta_from_pseudo_inertia((vec * np.maximum(lam, floor)) @ vec.T)
