"""Provably-safe exciting-trajectory planner (ARMOUR receding horizon, paper §VI). Pure math.

The planning problem of one call (constraints, costs, certificate) is problem.py's PlanningProblem,
its torque certificate torque_box.py; the reachability math lives in reachability.py,
interval_dynamics.py and affine_forms.py. This module is the planner that solves it.

One call plans one quintic Bézier (systems/math/bezier.py) from the current (q0, qd0, qdd0) to
q_end = q0 + k_c + k_r * k. Safety (continuous time, every theta in [theta], every tracking error
inside the controller's ultimate bound) comes from systems/planner/reachability.py:
- joint position / velocity limits -> a box of k (exact hull property);
- torque -> a rigorous interval-RNEA check over the whole k box (the box is shrunk if needed),
  robust input bounded on the whole tube, h < 0 included (reachability.torque_bound);
- collision -> one smooth constraint per (time interval, sphere, obstacle) pair that can be
  active, sd(c_s(q_mid_i(k)), obstacle) >= r_s + spread_is (pairs that no k can bring close are
  dropped, rigorously).
Cost: "exciting" = log cond of the stacked end-effector regressor W_e(k) at N_s instants (exact
gradient through the singular vectors; dW/dk by complex-step, exact to rounding: the regressor is
analytic in (q, qd, qdd) and dq/dk_j = w(t) k_r,j e_j), "goal" = |q_end - goal|^2, "random" =
random feasible k (the ablation). Solved with Drake MathematicalProgram (Ipopt or SNOPT) under an
iteration budget (config.budget "iterations": no clock read decides anything, so a seed replays
exactly) or, in the real-time mode "wall_time", also a wall-time cap; the best iterate that our own
constraint evaluation finds feasible is returned.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.config import Noise
from safesysid.systems.controller.armour import TrackingBounds
from safesysid.systems.math.bezier import QuinticBezier
from safesysid.systems.math.blas import single_threaded_blas
from safesysid.systems.model.robot_defaults import robot_defaults
from safesysid.systems.model.torque_noise import DeclaredTorqueNoise
from safesysid.systems.planner import reachability as reach
from safesysid.systems.planner.ee_regressor import ee_standard_regressor
from safesysid.systems.planner.problem import PlanningProblem

if TYPE_CHECKING:
    from safesysid.systems.config import Obstacle, Planner
    from safesysid.systems.model.payload import Dumbbell
    from safesysid.systems.model.robot_model import RobotModel

COLLISION_SOLVER_MARGIN_M = 1e-4

_CAP_MESSAGE = "planner wall-time cap reached"


class _WallTimeExceeded(Exception):
    """Raised from our callbacks to stop the solver at the wall-time cap (both Ipopt and SNOPT
    unwind cleanly; the best verified-feasible evaluated point is then used)."""


# ---------------------------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------------------------


@dataclass
class PlanResult:
    """Outcome of one planning call. `ok` is True only for a k verified feasible by our checks."""

    ok: bool
    status: str  # solved | best_feasible | random | infeasible | infeasible_start | solver_failed | planner_error
    reason: str = ""
    k: np.ndarray | None = None
    q_end: np.ndarray | None = None
    trajectory: QuinticBezier | None = None
    cost: float = float("nan")
    cond: float = float("nan")  # cond(W_e) of the plan (exciting cost = log cond)
    solve_time_s: float = 0.0  # wall time of the whole call (precompute + solve + verification)
    solver: str = ""
    solver_status: str = ""
    num_collision_constraints: int = 0
    k_box: tuple = ()
    min_clearance_m: float = float("nan")  # smallest verified collision slack
    max_torque_ratio: float = float("nan")  # sup |u| / limit over the plan (rigorous)
    details: dict = field(default_factory=dict)
    # (θ0, lower, upper) the plan was certified with when not the call's own: a wall-clock plan
    # is computed one period ahead, with the estimate of its submission (hardware/background.py).
    thetas: tuple | None = None

    def evaluate(self, t: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Desired q, qd, qdd (each (len(t), n)) at times t since the plan's start."""
        return self.trajectory.evaluate(t, self.q_end)


# The planner
# ---------------------------------------------------------------------------------------------


class SafePlanner:
    """ARMOUR-style planner for one robot, scene and payload.

    config: scenario `Planner` record (duration_s, num_time_intervals, num_cost_samples, cost,
    goal_q_rad, solver, max_solve_time_s, max_iterations, budget, k_center_rad, k_range_rad, floor_z_m).
    obstacles: scenario Obstacle records or a reachability.Boxes. payload: Dumbbell or None.
    tracking: controller.TrackingBounds (the controller's ultimate bound with ITS gains Kr; None
    means perfect tracking, for tests only). declared_noise: scenario.noise's declared torque-noise
    bound, which planner.exciting_weighting divides the cost's rows by (None: its default).
    """

    def __init__(
        self,
        robot: RobotModel,
        config: Planner,
        *,
        obstacles: Iterable[Obstacle] | reach.Boxes = (),
        payload: Dumbbell | None = None,
        tracking: TrackingBounds | None = None,
        floor: bool = True,
        torque_shrink_steps: int = 4,
        torque_group: int = 2,
        spread_rows: int = 4,
        declared_noise: DeclaredTorqueNoise | None = None,
    ) -> None:
        self.robot = robot
        self.config = config
        n = robot.n
        k_lists = {"planner.k_center_rad": config.k_center_rad, "planner.k_range_rad": config.k_range_rad}
        unset = [key for key, value in k_lists.items() if np.size(value) == 0]
        if unset:  # the robot's (a Planner made in code)
            k_lists |= robot_defaults(robot, unset)
        self.k_center = np.broadcast_to(np.asarray(k_lists["planner.k_center_rad"], float), (n,)).copy()
        self.k_range = np.broadcast_to(np.asarray(k_lists["planner.k_range_rad"], float), (n,)).copy()
        self.boxes = obstacles if isinstance(obstacles, reach.Boxes) else reach.Boxes.from_obstacles(list(obstacles))
        self.spheres = reach.arm_spheres(robot).concat(reach.payload_spheres(robot, payload))
        self.lipschitz = reach.sphere_lipschitz(robot.tree, self.spheres)
        self.floor_z = float(config.floor_z_m) if floor else None
        self.floor_exempt = reach.floor_exempt(robot.tree, self.spheres)
        self.tracking = TrackingBounds.coerce(tracking, n)
        self.torque_shrink_steps = torque_shrink_steps
        self.torque_group = torque_group
        self.spread_rows = spread_rows  # torque boxes per hull on which the M spread mu is bounded
        # The estimator's declared bound per sample (None: the scenario's default).
        self.declared_noise = declared_noise or DeclaredTorqueNoise.from_noise(Noise())

    @property
    def weighs_rows(self) -> bool:
        """planner.exciting_weighting noise: the exciting cost divides W_e's rows by row_weights."""
        return getattr(self.config, "exciting_weighting", "none") == "noise"

    def row_weights(self, q: np.ndarray, v: np.ndarray, a: np.ndarray, theta0: ArrayLike) -> np.ndarray:
        """1 / the declared torque-noise bound of each W_e row (samples x joints, flattened) of the
        nominal model theta0 along (q, v, a)."""
        tau = self.robot.inverse_dynamics(q, v, a, theta=np.asarray(theta0, float))
        return (1.0 / self.declared_noise.bound(tau)).ravel()

    def problem(
        self, q0: ArrayLike, v0: ArrayLike, a0: ArrayLike, *thetas: ArrayLike, **options: Any
    ) -> PlanningProblem:
        """The planning problem of one call from (q0, v0, a0) under the parameter box thetas =
        (theta0, theta_lo, theta_hi); options (PlanningProblem): mode, past, k_box (a sub-box, e.g.
        one point), certify_torque (False: no torque check, the wider solve of point_refinement),
        shrink_toward (where the torque check shrinks the box), box_scale (< 1: the limit box
        shrunk by it toward k = 0)."""
        return PlanningProblem(self, q0, v0, a0, *thetas, **options)

    def executed_rows(self, plan: PlanResult, duration_s: float, theta0: ArrayLike | None = None) -> np.ndarray:
        """W_e rows (rows, 10) of the first duration_s of an accepted plan, at the exciting cost's
        sample spacing, weighted as the cost weights its rows (row_weights under theta0, the
        robot's nominal when None): the `past` of the next planning call when
        planner.cumulative_excitation."""
        cfg = self.config
        t = np.arange(0.0, duration_s, cfg.duration_s / (cfg.num_cost_samples - 1))
        q, v, a = plan.evaluate(t)
        rows = ee_standard_regressor(self.robot.tree, self.robot.end_effector, q, v=v, a=a).reshape(-1, 10)
        if not self.weighs_rows:
            return rows
        return rows * self.row_weights(q, v, a, self.robot.theta if theta0 is None else theta0)[:, None]

    def plan(
        self,
        q0: ArrayLike,
        v0: ArrayLike,
        a0: ArrayLike,
        theta0: ArrayLike,
        theta_lo: ArrayLike,
        theta_hi: ArrayLike,
        *,
        k_init: ArrayLike | None = None,
        rng: np.random.Generator | None = None,
        mode: str | None = None,
        past: np.ndarray | None = None,
    ) -> PlanResult:
        """One planning call -> PlanResult (ok False: keep the previous plan, which brakes).
        past: W_e rows of the motion executed so far (executed_rows), for the exciting cost."""
        with single_threaded_blas():  # tall, thin matrices: more threads only spin
            return self._plan(q0, v0, a0, theta0, theta_lo, theta_hi, k_init, rng, mode, past)

    def _plan(self, q0, v0, a0, theta0, theta_lo, theta_hi, k_init, rng, mode, past):
        t_start = time.perf_counter()
        cpu_start = time.process_time()
        mode = mode or self.config.cost
        rng = rng or np.random.default_rng(0)
        res = PlanResult(
            ok=False, status="infeasible_start", solver=self.config.solver if mode != "random" else "random"
        )
        k = None
        if self.config.point_refinement:  # a plan certified on its own k; the k box only if none is
            refined = self._refine((q0, v0, a0, theta0, theta_lo, theta_hi, mode, past), k_init, rng, t_start)
            res.details["refined"] = refined is not None
            if refined is not None:
                k, prob, status, res.solver_status = refined
                res.k_box = (k.copy(), k.copy())
                res.num_collision_constraints = prob.num_pairs
                res.max_torque_ratio = prob.torque_ratio
        if k is None:
            prob = self.problem(q0, v0, a0, theta0, theta_lo, theta_hi, mode=mode, past=past)
            if prob.feasible_start:
                res.k_box = (prob.k_lo.copy(), prob.k_hi.copy())
                res.num_collision_constraints = prob.num_pairs
                res.max_torque_ratio = prob.torque_ratio
                if mode == "random":
                    k = self._random(prob, rng, self._deadline(t_start))
                    status, solver_status = "random", "sampled"
                else:
                    k, status, solver_status = self._optimize(prob, k_init, t_start)
                res.solver_status = solver_status
                if k is None:
                    res.status = "infeasible" if status != "solver_failed" else status
                    res.reason = f"no feasible k found ({solver_status})"
            else:
                res.reason = prob.reason
        if k is not None:
            vals, _ = prob.collision(k, with_jacobian=False)
            res.ok, res.status, res.k = True, status, k
            res.q_end = prob.reach.q_end(k)
            res.trajectory = prob.reach.bezier
            if res.details.get("refined"):  # its point problem keeps only the pairs within 1 mm
                res.min_clearance_m = prob.centre_clearance
            else:
                res.min_clearance_m = float(vals.min()) if len(vals) else float("inf")
            res.cost = prob.cost(k)[0] if mode != "random" else float("nan")
            res.cond = prob.cond(k)
            # Over-approximated swept spheres per time interval (for display): every point of
            # sphere s during interval i lies in the ball (centres[i, s], radii[i, s]).
            centres, _ = reach.sphere_centres(self.robot.tree, self.spheres, prob.reach.q_mid(k), with_jacobian=False)
            res.details["interval_edges_s"] = prob.reach.edges
            res.details["sphere_centres"] = centres
            res.details["sphere_radii"] = self.spheres.radius[None, :] + prob.spread
        res.solve_time_s = time.perf_counter() - t_start
        res.details["cpu_time_s"] = time.process_time() - cpu_start
        return res

    def _refine(self, args, k_init, rng, t_start):
        """A larger motion than a certified k box allows (planner.point_refinement): the box is
        certified for EVERY k in it, so its interval enclosures are wide and the box shrinks until
        they fit; one plan only needs its own k certified. Solve over the position/velocity limit
        box (planner.refinement_scale of it around k = 0) without the torque check (random: sample
        it), then take the farthest point
        toward that target, at 1, 7/8, ..., 1/8, 1/16 of the way from k = 0 (the limit box's point
        nearest to it), that the rigorous torque bound certifies on the point itself (the box
        machinery on point boxes, whose enclosures only span time and the tube), and check its
        collisions and limits as any plan's. (k, its problem, status, solver status) or None:
        then the caller plans in the certified box."""
        box, (mode, past) = args[:6], args[6:]  # (q0, v0, a0, theta0, theta_lo, theta_hi), options
        wide = self.problem(*box, mode=mode, past=past, certify_torque=False, box_scale=self.config.refinement_scale)
        if not wide.feasible_start:
            return None
        if mode == "random":
            target, status, solver_status = self._random(wide, rng, self._deadline(t_start)), "random", "sampled"
        else:
            target, status, solver_status = self._optimize(wide, k_init, t_start)
        if target is None:
            return None
        base = np.clip(np.zeros(self.n), wide.k_lo, wide.k_hi)
        for _ in range(1 + 3 * self.config.continuation):  # halved toward base while it cannot continue
            point = self.problem(*box, mode=mode, past=past, k_box=(target, target), shrink_toward=base)
            if not point.feasible_start:
                return None
            k = point.k_lo.copy()
            if not point.is_feasible(k):
                return None
            if not self.config.continuation or self._can_continue(point, k, args):
                return k, point, status, solver_status
            target = base + 0.5 * (k - base)
        return None

    def _can_continue(self, point, k, args):
        """planner.continuation: the plan k's state at the next call (t_p) has a certified plan
        of its own, k = 0, the last level the next call's refinement tries (with k_center 0 it holds
        still: it brakes to rest where it is), with this call's parameter box. A liveness check, not
        a safety one: every plan brakes anyway."""
        t_p = np.array([self.config.replan_period_s])
        q, v, a = (x[0] for x in point.desired_at(t_p, k))
        zero = np.zeros(self.n)
        nxt = self.problem(q, v, a, *args[3:6], mode=args[6], past=None, k_box=(zero, zero))
        return nxt.feasible_start and nxt.is_feasible(zero)

    def _initial_guess(self, prob, k_init, rng=None):
        """(start, fallback). Warm start from k_init; a plan that does not move at all makes W_e
        rank deficient (cost undefined), so also try alternating half-range moves, preferring a
        feasible guess. fallback: some verified-feasible k (any cost) or None."""
        pattern = 0.5 * np.where(np.arange(self.n) % 2 == 0, 1.0, -1.0)
        cands = ([] if k_init is None else [np.asarray(k_init, float)]) + [pattern, -pattern, np.zeros(self.n)]
        cands = [np.clip(c, prob.k_lo, prob.k_hi) for c in cands]
        usable, fallback = [], None
        for c in cands:
            val = prob.cost(c)[0] if prob.mode != "random" else 0.0
            ok = np.isfinite(val) and val < 25.0  # cond < 7e10: the gradient is meaningful
            feasible = prob.is_feasible(c)
            if ok and feasible:
                return c, c
            if ok:
                usable.append(c)
            if feasible and fallback is None:
                fallback = c
        rng = rng or np.random.default_rng(0)
        for _ in range(20):  # a few random points of the box, for a feasible start
            c = rng.uniform(prob.k_lo, prob.k_hi)
            if prob.is_feasible(c):
                return c, c
        return (usable[0] if usable else cands[0]), fallback

    def _deadline(self, t_start):
        """perf_counter time at which a call stops: the wall-time cap in the real-time mode, never
        in the iteration-budget mode (there the solver's iteration limit alone ends it)."""
        return t_start + self.config.max_solve_time_s if self.config.budget == "wall_time" else np.inf

    # -- random feasible k (ablation) ------------------------------------------------------------
    def _random(self, prob, rng, deadline, tries=200):
        for _ in range(tries):
            k = rng.uniform(prob.k_lo, prob.k_hi)
            if prob.is_feasible(k):
                return k
            if time.perf_counter() > deadline:
                break
        return None

    # -- optimization ----------------------------------------------------------------------------
    def _optimize(self, prob, k_init, t_start):
        """(k, status, solver status): Drake's solver on the problem from a warm start, then the best
        verified-feasible point among its answer and every point it evaluated."""
        from pydrake.solvers import MathematicalProgram

        deadline = self._deadline(t_start)
        evals = _Evaluations(prob, deadline)
        prog = MathematicalProgram()
        k = prog.NewContinuousVariables(self.n, "k")
        prog.AddBoundingBoxConstraint(prob.k_lo, prob.k_hi, k)
        prog.AddCost(evals.cost_fn, k)
        if prob.num_constraints:
            m = prob.num_constraints
            prog.AddConstraint(evals.con_fn, np.full(m, COLLISION_SOLVER_MARGIN_M), np.full(m, np.inf), k)
        k0, fallback = self._initial_guess(prob, k_init)
        prog.SetInitialGuess(k, k0)
        remaining = max(0.05, deadline - time.perf_counter())  # inf: no time limit for the solver
        solver, options = _solver_and_options(self.config, mode=prob.mode, remaining_s=remaining)
        cands = []
        try:
            result = solver.Solve(prog, k0, options)
            status = str(result.get_solution_result()).split(".")[-1]
            x_sol = np.clip(result.GetSolution(k), prob.k_lo, prob.k_hi)
            cands.append((evals.cost_eval(x_sol)[0], x_sol, "solved" if result.is_success() else "best_feasible"))
        except _WallTimeExceeded:
            status = "wall_time_cap"
        except Exception as err:  # noqa: BLE001 -- solver failure: fall back on what was evaluated
            status = "wall_time_cap" if _CAP_MESSAGE in str(err) else f"solver error: {str(err).splitlines()[0]}"
        if status.startswith("solver error") and not evals.record:
            return None, "solver_failed", status
        # Candidates: the solver's answer and every evaluated point; keep the best verified feasible.
        cands += evals.feasible_points()
        cands.append((prob.cost(k0)[0], k0, "best_feasible"))
        if fallback is not None:  # safe but maybe dull (e.g. holding still): better than braking
            cands.append((np.inf, fallback, "best_feasible"))
        cands.sort(key=lambda item: item[0])
        for _, x, st in cands:
            if prob.is_feasible(x):
                return np.array(x), st, status
        return None, "infeasible", status

    @property
    def n(self) -> int:
        return self.robot.n


class _Evaluations:
    """The solver's callbacks on one problem: cached cost and grouped collision constraints (plain
    floats or AutoDiffXd), each evaluated point's cost and least slack recorded (the candidates
    when the solver fails or stops), and the wall-time cap checked on every call."""

    def __init__(self, prob, deadline):
        self.prob = prob
        self.deadline = deadline
        self.record = {}  # x bytes -> [cost, min slack]
        self.con_cache = {}

    def check_time(self):
        if self.deadline < np.inf and time.perf_counter() > self.deadline:
            raise _WallTimeExceeded(_CAP_MESSAGE)

    def cost_eval(self, x):
        kk = np.asarray(x, float).tobytes()
        if kk not in self.prob._cache:
            self.prob._cache[kk] = self.prob.cost(x)
        val, grad = self.prob._cache[kk]
        self.record.setdefault(kk, [None, None])[0] = val
        return val, grad

    def con_eval(self, x):
        kk = np.asarray(x, float).tobytes()
        if kk not in self.con_cache:
            self.con_cache[kk] = self.prob.collision_grouped(x)
        vals, jac = self.con_cache[kk]
        self.record.setdefault(kk, [None, None])[1] = vals.min() if len(vals) else np.inf
        return vals, jac

    def cost_fn(self, x):
        self.check_time()
        if x.dtype == object:
            from pydrake.autodiffutils import AutoDiffXd, ExtractGradient, ExtractValue

            val, grad = self.cost_eval(ExtractValue(x)[:, 0])
            return AutoDiffXd(val, grad @ ExtractGradient(x))
        return self.cost_eval(x)[0]

    def con_fn(self, x):
        self.check_time()
        if x.dtype == object:
            from pydrake.autodiffutils import ExtractGradient, ExtractValue, InitializeAutoDiff

            vals, jac = self.con_eval(ExtractValue(x)[:, 0])
            return InitializeAutoDiff(vals, jac @ ExtractGradient(x))[:, 0]
        return self.con_eval(x)[0]

    def feasible_points(self):
        """(cost, k, "best_feasible") of every evaluated point whose constraints the solver saw met."""
        return [
            (c, np.frombuffer(kk), "best_feasible")
            for kk, (c, slack) in self.record.items()
            if c is not None and slack is not None and slack >= 0
        ]


def _solver_and_options(config: Planner, *, mode: str, remaining_s: float):
    """The configured solver (SNOPT or Ipopt) and its options: the iteration budget, the time left
    (inf: none), tolerances."""
    from pydrake.solvers import IpoptSolver, SnoptSolver, SolverOptions

    options = SolverOptions()
    if config.solver == "snopt":
        solver = SnoptSolver()
        sid = solver.solver_id()
        options.SetOption(sid, "Major iterations limit", int(config.max_iterations))
        if remaining_s < np.inf:
            options.SetOption(sid, "Time limit", float(remaining_s))
        options.SetOption(sid, "Major optimality tolerance", 1e-4)
        options.SetOption(sid, "Major feasibility tolerance", 1e-6)
        return solver, options
    solver = IpoptSolver()
    sid = solver.solver_id()
    options.SetOption(sid, "max_iter", int(config.max_iterations))
    if remaining_s < np.inf:
        options.SetOption(sid, "max_wall_time", float(remaining_s))
    options.SetOption(sid, "hessian_approximation", "limited-memory")
    if mode == "exciting":
        # log cond is nonsmooth where the two smallest singular values cross, so the dual
        # infeasibility may never vanish: stop once the objective stalls (3 feasible
        # iterations changing log cond by < 0.003): a slightly better cond is not worth more time.
        options.SetOption(sid, "tol", 1e-3)
        options.SetOption(sid, "acceptable_tol", 1e6)
        options.SetOption(sid, "acceptable_iter", 3)
        options.SetOption(sid, "acceptable_obj_change_tol", 3e-3)
    else:
        options.SetOption(sid, "tol", 1e-8)
    options.SetOption(sid, "constr_viol_tol", 1e-6)
    options.SetOption(sid, "acceptable_constr_viol_tol", 1e-6)
    options.SetOption(sid, "print_level", int(os.environ.get("SAFESYSID_IPOPT_PRINT", 0)))
    options.SetOption(sid, "mu_strategy", "monotone")
    options.SetOption(sid, "mu_init", 1e-3)
    return solver, options
