"""Task trajectory (paper §VII, "Trajectory for Executing Tasks"). Pure math, no LeafSystem.

After identification the arm follows a trajectory computed offline: minimum jerk, `num_pieces`
degree-5 Bézier pieces of equal length (paper: two 1-s pieces), C2 at the junctions, from rest
at q_start to rest at a goal, respecting joint position/velocity limits, torque limits and
collision avoidance for the payload model (paper: the 8 lb dumbbell).

Goal: a joint configuration, or a placement (payload centre at a point, gripper vertical, so the
dumbbell's handle is horizontal). A placement is solved first with Drake InverseKinematics
(nearest to q_start: reachability check and initial guess), then the goal configuration stays a
decision variable of the trajectory optimization, constrained to the placement (folded in).

Decision variables y = [Z (r x n, row-major), q_goal (n)]: all control points X (6K x n) are
X = N Z + g_s q_start^T + g_g q_goal^T, N a basis of the null space of the boundary and
junction equalities (rest at both ends: three equal control points; C0, C1, C2 at junctions).

Cost: sum_j int |d^3 q_j / dt^3|^2 dt, exact quadratic in the control points (third derivative
of a quintic piece = quadratic Bézier; Gram matrix of the degree-2 Bernstein basis).

Constraints (the trajectory is a REFERENCE the ARMOUR controller tracks inside its certified tube;
what is asked here is feasibility with room for that tube, TrackingBounds of the controller):
- position / velocity limits: every control point of q (and of dq/dt) inside the limits shrunk by
  the tube's position (velocity) bound: exact in continuous time (Bézier hull property);
- torque: nominal inverse dynamics of the payload model at `torque_samples` instants,
  |tau_j| <= (1 - torque_margin_ratio) limit_j (room for the feedback and robust terms);
- collision: each planner sphere (models/kinova_gen3_spheres.yaml + the payload's covering
  spheres) against each box and the floor at `collision_samples` instants t_i, each covering
  [t_i - h/2, t_i + h/2]: sd(centre, box) >= radius + spread, with spread the sphere's
  displacement bound over that window and the tube (reachability.local_spread: joint motion
  <= (velocity bound) h/2 + tube position bound, times the local Jacobian bound). Since the
  velocity constraint is exact, this holds in continuous time for the spheres.
The solver sees one soft-min per (sphere, obstacle) over the samples (<= the true min); every
(sample, sphere, obstacle) value is checked at the solution.

Solved with Drake MathematicalProgram: SNOPT first, Ipopt as fallback. `verify_task_trajectory`
re-checks a solution independently: Drake signed distance between the link shapes + payload
(the referee's geometry, systems/plant/safety_monitor.py) and the obstacles/floor at 1 kHz, Drake's
CalcInverseDynamics (+ the plant's joint friction), limits.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.math.piecewise_bezier import PiecewiseBezier
from safesysid.systems.task.constraints import GRIPPER_TILT_TOL_RAD, PLACEMENT_TOL_M, TaskConstraints
from safesysid.systems.task.problem import TaskProblem, TaskSettings, jsonable

if TYPE_CHECKING:
    from safesysid.systems.config import Obstacle, Scenario
    from safesysid.systems.model.payload import Dumbbell


VERSION = "task_trajectory/1"  # part of the cache key: bump when the formulation changes
SOLVER_MARGIN = 1e-4  # the solver aims this far inside the collision / placement constraints
FEASIBILITY_TOL = 1e-6  # max violation accepted when our own evaluation re-checks a solution


# ---------------------------------------------------------------------------------------------
# Result
# ---------------------------------------------------------------------------------------------
@dataclass
class TaskResult:
    ok: bool
    status: str  # solved | feasible | infeasible | goal_unreachable | goal_blocked | start_blocked | solver_failed
    reason: str = ""
    trajectory: PiecewiseBezier | None = None
    q_goal: np.ndarray | None = None
    cost: float = float("nan")  # integrated squared jerk [rad^2 / s^5]
    max_violation: float = float("nan")  # of our own constraint evaluation (0: all satisfied)
    min_sphere_clearance_m: float = float("nan")  # min over samples of sd - radius - spread
    max_torque_ratio: float = float("nan")  # max |tau| / limit at the torque samples
    solve_time_s: float = 0.0
    solver: str = ""
    solver_status: str = ""
    details: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        out = {
            k: getattr(self, k)
            for k in (
                "ok",
                "status",
                "reason",
                "cost",
                "max_violation",
                "min_sphere_clearance_m",
                "max_torque_ratio",
                "solve_time_s",
                "solver",
                "solver_status",
            )
        }
        out["q_goal_rad"] = None if self.q_goal is None else self.q_goal.tolist()
        out["trajectory"] = None if self.trajectory is None else self.trajectory.to_dict()
        out["details"] = jsonable(self.details)
        return out

    @classmethod
    def from_dict(cls, doc: dict) -> TaskResult:
        doc = dict(doc)
        q_goal, traj = doc.pop("q_goal_rad"), doc.pop("trajectory")
        return cls(
            q_goal=None if q_goal is None else np.asarray(q_goal, float),
            trajectory=None if traj is None else PiecewiseBezier.from_dict(traj),
            **doc,
        )


def task_problem_from_scenario(scenario: Scenario, q_start: ArrayLike | None = None) -> TaskProblem:
    """TaskProblem of a scenario's `task` section (start: q0_rad, the identification start).

    Torque model: the robot plus the `task.payload_model` dumbbell (exact, nominal); collision:
    the planner's spheres + that dumbbell's; tube: the ARMOUR controller's TrackingBounds for the
    scenario's gains and prior (as app/online.py gives the planner).
    """
    from safesysid.systems.config import ScenarioError, task_enabled
    from safesysid.systems.controller.armour import tracking_bounds_for
    from safesysid.systems.controller.systems import gains_from_scenario
    from safesysid.systems.model.loading import resolve_path, robot_from_scenario, scenario_dir
    from safesysid.systems.model.payload import load_dumbbells
    from safesysid.systems.model.uncertainty import prior_box
    from safesysid.systems.plant.arm_plant import true_theta

    where = scenario.source or "scenario"
    if not task_enabled(scenario):
        raise ScenarioError(f"{where}: task: no goal_q_rad, place_xyz_m or platform")
    task = scenario.task
    robot = robot_from_scenario(scenario)
    dumbbell = load_dumbbells(resolve_path(scenario.payload.dumbbells_file, scenario_dir(scenario)))[task.payload_model]
    _, box = prior_box(robot, scenario.initial_interval, scenario.noise)
    tracking = tracking_bounds_for(robot, gains_from_scenario(scenario, robot.n).armour, box.lo)
    place = None
    if not task.goal_q_rad:
        place = (
            np.asarray(task.place_xyz_m, float)
            if task.place_xyz_m
            else placement_above(
                next(ob for ob in scenario.obstacles if ob.name == task.platform), dumbbell, task.release_height_m
            )
        )
    return TaskProblem(
        robot=robot,
        theta=true_theta(robot, dumbbell),
        dumbbell=dumbbell,
        obstacles=list(scenario.obstacles),
        floor_z=scenario.planner.floor_z_m,
        q_start=scenario.q0_rad if q_start is None else q_start,
        goal_q=task.goal_q_rad or None,
        place_xyz=place,
        tracking=tracking,
        settings=TaskSettings.from_task(task),
    )


def placement_above(platform: Obstacle, dumbbell: Dumbbell | None, release_height: float) -> np.ndarray:
    """Payload centre above the platform's top centre with its lowest point release_height above
    the top (handle horizontal: the heads' radius below the centre). Platform: an axis-aligned
    box (scenario Obstacle); a rotated one uses its top face's highest corner."""
    from pydrake.math import RollPitchYaw

    rot = RollPitchYaw(platform.rpy_rad).ToRotationMatrix().matrix()
    top = (np.abs(rot) @ (0.5 * np.asarray(platform.size_m, float)))[2]  # half height of the rotated box
    below = max(dumbbell.head_radius_m, dumbbell.handle_radius_m) if dumbbell is not None else 0.0
    return np.asarray(platform.xyz_m, float) + np.array([0.0, 0.0, top + below + release_height])


# ---------------------------------------------------------------------------------------------
# Inverse kinematics of a placement (Drake)
# ---------------------------------------------------------------------------------------------
def solve_placement_ik(problem: TaskProblem, q_guess: ArrayLike | None = None) -> tuple[np.ndarray | None, str]:
    """Goal configuration for problem.place_xyz nearest to q_start, gripper vertical (Drake
    InverseKinematics). Returns (q or None, message)."""
    from pydrake.multibody.inverse_kinematics import InverseKinematics
    from pydrake.solvers import Solve
    from safesysid.systems.model.robot_model import make_plant

    robot = problem.robot
    plant, _, _ = make_plant(robot.source)
    plant.Finalize()
    ee = plant.GetBodyByName(robot.body_names[robot.end_effector]).body_frame()
    target = problem.place_xyz
    tb = problem.tracking
    jp = robot.joint_params
    best, msg = None, "no initial guess converged"
    starts = [problem.q_start] if q_guess is None else [np.asarray(q_guess, float), problem.q_start]
    # A second start turned towards the target about the base axis (a different IK branch).
    turned = problem.q_start.copy()
    turned[0] = np.arctan2(target[1], target[0])
    for q0 in starts + [turned]:
        ik = InverseKinematics(plant, with_joint_limits=False)
        q = ik.q()
        ik.AddPositionConstraint(
            ee,
            np.asarray(robot.extra["grasp_point"], float),
            plant.world_frame(),
            target - PLACEMENT_TOL_M / 2,
            target + PLACEMENT_TOL_M / 2,
        )
        ik.AddAngleBetweenVectorsConstraint(
            plant.world_frame(), [0.0, 0.0, 1.0], ee, [0.0, 0.0, 1.0], 0.0, GRIPPER_TILT_TOL_RAD / 2
        )
        lo = np.where(np.isfinite(jp.position_lower), jp.position_lower + tb.position, -np.inf)
        hi = np.where(np.isfinite(jp.position_upper), jp.position_upper - tb.position, np.inf)
        prog = ik.get_mutable_prog()
        prog.AddBoundingBoxConstraint(lo, hi, q)
        prog.AddQuadraticErrorCost(np.eye(robot.n), problem.q_start, q)
        result = Solve(prog, q0)
        if result.is_success():
            sol = result.GetSolution(q)
            if best is None or np.sum((sol - problem.q_start) ** 2) < np.sum((best - problem.q_start) ** 2):
                best = sol
        else:
            msg = f"InverseKinematics: {result.get_solution_result()}".replace("SolutionResult.", "")
    return best, ("" if best is not None else msg)


# ---------------------------------------------------------------------------------------------
# Optimization
# ---------------------------------------------------------------------------------------------
def solve_task_trajectory(problem: TaskProblem, solver: str | None = None, fallback: bool = True) -> TaskResult:
    """Minimum-jerk task trajectory (see the module docstring). solver: snopt | ipopt (default:
    problem.settings.solver); with fallback, the other solver is tried when the first fails our
    own check. Never raises for an infeasible or unreachable goal: the status says why."""
    t0 = time.perf_counter()
    solver = solver or problem.settings.solver
    con = TaskConstraints(problem)
    res = TaskResult(ok=False, status="start_blocked", solver=solver)
    details = res.details
    clear, what = con.rest_clearance(problem.q_start)
    if clear < 0:
        res.reason = f"q_start is {-clear:.4f} m inside the margin: {what}"
        return _finish(res, t0)
    if problem.place_xyz is not None:
        q_goal, msg = solve_placement_ik(problem)
        details["ik_time_s"] = time.perf_counter() - t0
        if q_goal is None:
            res.status, res.reason = "goal_unreachable", f"placement {problem.place_xyz.tolist()} m: {msg}"
            return _finish(res, t0)
        details["q_goal_ik_rad"] = q_goal
    else:
        q_goal = problem.goal_q
        clear, what = con.rest_clearance(q_goal)
        if clear < 0:
            res.status, res.reason = "goal_blocked", f"goal_q is {-clear:.4f} m inside the margin: {what}"
            return _finish(res, t0)
    y0 = con.initial_guess(q_goal)
    order = [solver] + ([s for s in ("snopt", "ipopt") if s != solver] if fallback else [])
    attempts = []
    for name in order:
        t_solve = time.perf_counter()
        y, status, rounds = _solve_rounds(con, y0, name)
        viol, clearance, torque_ratio = con.check(y) if y is not None else (np.inf, np.nan, np.nan)
        attempts.append(
            {
                "solver": name,
                "solver_status": status,
                "rounds": rounds,
                "time_s": time.perf_counter() - t_solve,
                "max_violation": viol,
            }
        )
        res.solver, res.solver_status, res.max_violation = name, status, viol
        if y is not None and viol <= FEASIBILITY_TOL:
            # solved: the solver reports an optimum; feasible: it did not, our check passes
            res.ok, res.status = True, "solved" if status == "kSolutionFound" else "feasible"
            res.trajectory, res.q_goal = con.trajectory(y), con.split(y)[1]
            res.cost = con.cost(y)
            res.min_sphere_clearance_m, res.max_torque_ratio = clearance, torque_ratio
            break
    details["attempts"] = attempts
    if not res.ok:
        res.status = "solver_failed" if all(a["solver_status"].startswith("error") for a in attempts) else "infeasible"
        res.reason = "; ".join(
            f"{a['solver']}: {a['solver_status']}, max violation {a['max_violation']:.3g}" for a in attempts
        )
    return _finish(res, t0)


def _solve_rounds(con: TaskConstraints, y0, solver_name, max_rounds=4):
    """Solver rounds with fixed collision margins (the spreads, which depend on y) and the torque
    rows only once needed (they cost 3/4 of an evaluation and are rarely active): after each
    round our own check at the solution; if it fails, the margins grow to cover the solution's
    (max with the previous: monotone, so the rounds settle) and the torque rows are added if
    torque was violated; warm start from the last solution. -> (y, status, rounds)."""
    spread, with_torque, y, status = con.spread(y0), False, y0, ""
    deadline = time.perf_counter() + con.p.settings.max_solve_time_s
    for k in range(max_rounds):
        remaining = deadline - time.perf_counter()
        if remaining <= 0:
            return y, f"{status}, wall-time cap", k
        y_new, status = _solve_with(con, y, solver_name, spread, with_torque, remaining)
        if y_new is None:
            return None, status, k + 1
        y = y_new
        viol, _, torque_ratio = con.check(y)
        if viol <= FEASIBILITY_TOL:
            return y, status, k + 1
        grown = np.maximum(spread, con.spread(y))
        needs_torque = torque_ratio > 1.0 - con.p.settings.torque_margin_ratio
        if np.array_equal(grown, spread) and (with_torque or not needs_torque):
            break  # nothing to adjust: the solver itself did not reach a feasible point
        spread, with_torque = grown, with_torque or needs_torque
    return y, status, k + 1


def _finish(res, t0):
    res.solve_time_s = time.perf_counter() - t0
    return res


def _solve_with(con: TaskConstraints, y0, solver_name, spread, with_torque=True, time_limit_s=np.inf):
    """One solver run from y0 with collision margins `spread` -> (y or None, solver status)."""
    from pydrake.autodiffutils import ExtractGradient, ExtractValue, InitializeAutoDiff
    from pydrake.solvers import IpoptSolver, MathematicalProgram, SnoptSolver, SolverOptions

    p = con.p
    n, r = con.n, con.param.r
    prog = MathematicalProgram()
    y = prog.NewContinuousVariables(con.num_vars, "y")
    z, q_goal = y[:-n].reshape(r, n), y[-n:]
    for j, (qm, b, c) in enumerate(con.cost_matrices()):
        prog.AddQuadraticCost(qm, b, c, np.concatenate([z[:, j], [q_goal[j]]]), is_convex=True)
    for a, const, lo, hi, j in con.hull_rows():
        prog.AddLinearConstraint(a, lo - const, hi - const, np.concatenate([z[:, j], [q_goal[j]]]))

    def wrap(fn):
        def call(x):
            if x.dtype == object:
                vals, jac = fn(ExtractValue(x)[:, 0])
                return InitializeAutoDiff(vals, jac @ ExtractGradient(x))[:, 0]
            return fn(x)[0]

        return call

    if p.place_xyz is not None:
        tol = np.array([PLACEMENT_TOL_M - SOLVER_MARGIN / 10] * 3)
        prog.AddConstraint(
            wrap(con.placement),
            np.concatenate([-tol, [-np.inf]]),
            np.concatenate([tol, [1 - np.cos(GRIPPER_TILT_TOL_RAD / 2)]]),
            q_goal,
        )
    else:
        prog.AddBoundingBoxConstraint(p.goal_q, p.goal_q, q_goal)

    def collision(x):
        return con.collision_grouped(x, spread)

    m = len(collision(y0)[0])
    if m:
        prog.AddConstraint(wrap(collision), np.full(m, SOLVER_MARGIN), np.full(m, np.inf), y)

    def torque_flat(x):
        vals, jac = con.torque(x)
        return vals.ravel(), jac

    if with_torque:
        nt = len(con.t_tau) * n
        prog.AddConstraint(wrap(torque_flat), -np.ones(nt), np.ones(nt), y)
    options = SolverOptions()
    iters = int(p.settings.max_iterations)
    if solver_name == "snopt":
        solver = SnoptSolver()
        sid = solver.solver_id()
        options.SetOption(sid, "Major iterations limit", iters)
        options.SetOption(sid, "Major optimality tolerance", 1e-5)
        options.SetOption(sid, "Major feasibility tolerance", 1e-7)
        options.SetOption(sid, "Time limit", float(min(time_limit_s, 1e6)))
    else:
        solver = IpoptSolver()
        sid = solver.solver_id()
        options.SetOption(sid, "max_iter", iters)
        options.SetOption(sid, "tol", 1e-6)
        options.SetOption(sid, "constr_viol_tol", 1e-7)
        options.SetOption(sid, "mu_strategy", "adaptive")
        options.SetOption(sid, "max_wall_time", float(min(time_limit_s, 1e6)))
        # The soft-min of many samples is stiff for a limited-memory Hessian: the dual
        # infeasibility may stay large while the objective no longer moves. Stop after 5 feasible
        # iterations changing the jerk by < 1e-4 (relative); the check decides feasibility.
        options.SetOption(sid, "acceptable_tol", 1e10)
        options.SetOption(sid, "acceptable_iter", 5)
        options.SetOption(sid, "acceptable_constr_viol_tol", 1e-7)
        options.SetOption(sid, "acceptable_obj_change_tol", 1e-4)
        options.SetOption(sid, "hessian_approximation", "limited-memory")
        options.SetOption(sid, "print_level", int(os.environ.get("SAFESYSID_IPOPT_PRINT", 0)))
    try:
        result = solver.Solve(prog, y0, options)
    except Exception as err:  # noqa: BLE001 -- a solver failure is a status, not a crash
        return None, f"error: {str(err).splitlines()[0]}"
    return result.GetSolution(y), str(result.get_solution_result()).replace("SolutionResult.", "")
