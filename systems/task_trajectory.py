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
(the referee's geometry, systems/safety_monitor.py) and the obstacles/floor at 1 kHz, Drake's
CalcInverseDynamics (+ the plant's joint friction), limits.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from math import comb
from pathlib import Path

import numpy as np

from . import reachability as reach
from .armour import TrackingBounds
from .bezier import _bernstein, _difference, restriction_matrix

VERSION = "task_trajectory/1"  # part of the cache key: bump when the formulation changes
DEGREE = 5
SOFTMIN_SHARPNESS_PER_M = 2000.0  # soft-min <= min, gap <= log(samples) / beta (2.6 mm at 200)
SOLVER_MARGIN = 1e-4  # the solver aims this far inside the collision / placement constraints
FEASIBILITY_TOL = 1e-6  # max violation accepted when our own evaluation re-checks a solution
PLACEMENT_TOL_M = 1e-4  # placement equality as a box of this half-width
GRIPPER_TILT_TOL_RAD = 1e-3  # gripper axis vs vertical at a placement


# ---------------------------------------------------------------------------------------------
# Piecewise Bézier
# ---------------------------------------------------------------------------------------------
@dataclass
class PiecewiseBezier:
    """K degree-5 pieces of equal duration; control_points (K, 6, n)."""

    control_points: np.ndarray
    piece_duration: float

    @property
    def num_pieces(self):
        return self.control_points.shape[0]

    @property
    def duration(self):
        return self.num_pieces * self.piece_duration

    def evaluate(self, t, orders=3):
        """[q, dq/dt, d2q/dt2, ...] (orders + 1 arrays (len(t), n)); at rest outside [0, T]."""
        t = np.atleast_1d(np.asarray(t, float))
        x = self.control_points.reshape(-1, self.control_points.shape[-1])
        out = [basis(t, self.num_pieces, self.piece_duration, k) @ x for k in range(orders + 1)]
        outside = ((t < 0) | (t > self.duration))[:, None]
        return [out[0]] + [np.where(outside, 0.0, d) for d in out[1:]]

    def to_dict(self):
        return {"piece_duration_s": self.piece_duration, "control_points_rad": self.control_points.tolist()}

    @classmethod
    def from_dict(cls, doc):
        return cls(np.asarray(doc["control_points_rad"], float), float(doc["piece_duration_s"]))


def basis(t, num_pieces, piece_duration, order=0):
    """B (len(t), 6K): the order-th time derivative of the curve at t is B @ X (X: (6K, n))."""
    t = np.clip(np.atleast_1d(np.asarray(t, float)), 0.0, num_pieces * piece_duration)
    piece = np.minimum((t // piece_duration).astype(int), num_pieces - 1)
    s = t / piece_duration - piece
    local = _bernstein(DEGREE - order, s) @ _difference(np.eye(DEGREE + 1), order) / piece_duration**order
    out = np.zeros((len(t), (DEGREE + 1) * num_pieces))
    for k in range(DEGREE + 1):
        out[np.arange(len(t)), 6 * piece + k] = local[:, k]
    return out


def jerk_gram(num_pieces, piece_duration):
    """Q (6K, 6K): sum_j int |jerk_j|^2 dt = sum_j x_j^T Q x_j (exact)."""
    d3 = _difference(np.eye(DEGREE + 1), 3) / piece_duration**3  # (3, 6): jerk control points
    g = np.array([[comb(2, i) * comb(2, j) / (5.0 * comb(4, i + j)) for j in range(3)] for i in range(3)])
    block = piece_duration * d3.T @ g @ d3  # int over the piece: T int_0^1 ds
    return np.kron(np.eye(num_pieces), block)


@dataclass
class Parametrization:
    """X = N Z + g_s q_start^T + g_g q_goal^T: every control-point matrix of K pieces with rest at
    both ends and C0, C1, C2 junctions (equal durations, so equal control-point differences)."""

    null: np.ndarray  # (6K, r)
    g_start: np.ndarray  # (6K,)
    g_goal: np.ndarray  # (6K,)

    @classmethod
    def make(cls, num_pieces):
        from scipy.linalg import null_space

        m = 6 * num_pieces
        rows, rhs = [], []  # rhs: 0 none, 1 q_start, 2 q_goal

        def row(entries, side=0):
            r = np.zeros(m)
            for idx, val in entries:
                r[idx] += val
            rows.append(r)
            rhs.append(side)

        for k in range(3):  # rest at the start: P0 = P1 = P2 = q_start; at the end likewise
            row([(k, 1.0)], 1)
            row([(m - 1 - k, 1.0)], 2)
        for p in range(num_pieces - 1):
            a, b = 6 * p, 6 * (p + 1)
            for order in range(3):  # derivative `order` at s = 1 of piece p equals it at s = 0 of p + 1
                end, start = _difference(np.eye(6), order)[[-1, 0]]
                row([(a + i, end[i]) for i in range(6)] + [(b + i, -start[i]) for i in range(6)])
        e = np.array(rows)
        f = np.array(rhs)
        pinv = np.linalg.pinv(e)
        return cls(null_space(e), pinv @ (f == 1).astype(float), pinv @ (f == 2).astype(float))

    @property
    def r(self):
        return self.null.shape[1]

    def control_points(self, z, q_start, q_goal):
        return self.null @ z + np.outer(self.g_start, q_start) + np.outer(self.g_goal, q_goal)


# ---------------------------------------------------------------------------------------------
# Problem and result
# ---------------------------------------------------------------------------------------------
@dataclass
class TaskSettings:
    """Numbers of the optimization (scenario `task` section, app/scenario.py)."""

    duration_s: float = 2.0
    num_pieces: int = 2
    collision_samples: int = 200
    torque_samples: int = 41
    torque_margin_ratio: float = 0.2
    solver: str = "snopt"
    max_iterations: int = 500
    max_solve_time_s: float = 120.0  # per solver (all its rounds)

    @classmethod
    def from_task(cls, task):
        return cls(**{f: getattr(task, f) for f in cls.__dataclass_fields__})


@dataclass
class TaskProblem:
    """Everything the task trajectory depends on (and the cache key hashes)."""

    robot: object  # RobotModel (limits, friction, kinematics)
    theta: np.ndarray  # 14 n parameters the torque is computed with (robot + payload model)
    dumbbell: object  # payload model (payload.Dumbbell) or None
    obstacles: list  # scenario Obstacle records (platform included)
    floor_z: float | None
    q_start: np.ndarray
    goal_q: np.ndarray | None = None
    place_xyz: np.ndarray | None = None  # payload centre target (grasp point), base frame
    tracking: TrackingBounds | None = None
    settings: TaskSettings = field(default_factory=TaskSettings)

    def __post_init__(self):
        n = self.robot.n
        self.q_start = np.asarray(self.q_start, float)
        self.goal_q = None if self.goal_q is None or len(self.goal_q) == 0 else np.asarray(self.goal_q, float)
        self.place_xyz = (
            None if self.place_xyz is None or len(self.place_xyz) == 0 else np.asarray(self.place_xyz, float)
        )
        if (self.goal_q is None) == (self.place_xyz is None):
            raise ValueError("a task needs exactly one of goal_q and place_xyz")
        self.tracking = TrackingBounds.coerce(self.tracking, n)
        self.boxes = reach.Boxes.from_obstacles(list(self.obstacles))
        self.spheres = reach.arm_spheres(self.robot).concat(reach.payload_spheres(self.robot, self.dumbbell))


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

    def to_dict(self):
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
        out["details"] = _jsonable(self.details)
        return out

    @classmethod
    def from_dict(cls, doc):
        doc = dict(doc)
        q_goal, traj = doc.pop("q_goal_rad"), doc.pop("trajectory")
        return cls(
            q_goal=None if q_goal is None else np.asarray(q_goal, float),
            trajectory=None if traj is None else PiecewiseBezier.from_dict(traj),
            **doc,
        )


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def task_problem_from_scenario(scenario, q_start=None):
    """TaskProblem of a scenario's `task` section (start: q0_rad, the identification start).

    Torque model: the robot plus the `task.payload_model` dumbbell (exact, nominal); collision:
    the planner's spheres + that dumbbell's; tube: the ARMOUR controller's TrackingBounds for the
    scenario's gains and prior (as app/online.py gives the planner).
    """
    from .armour import prior_box, tracking_bounds_for
    from .config import ScenarioError, resolve_path, robot_from_scenario, scenario_dir, task_enabled
    from .controller_systems import gains_from_scenario
    from .payload import load_dumbbells
    from .real_arm import true_theta

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


def placement_above(platform, dumbbell, release_height):
    """Payload centre above the platform's top centre with its lowest point release_height above
    the top (handle horizontal: the heads' radius below the centre). Platform: an axis-aligned
    box (scenario Obstacle); a rotated one uses its top face's highest corner."""
    from pydrake.math import RollPitchYaw

    rot = RollPitchYaw(platform.rpy_rad).ToRotationMatrix().matrix()
    top = (np.abs(rot) @ (0.5 * np.asarray(platform.size_m, float)))[2]  # half height of the rotated box
    below = max(dumbbell.head_radius_m, dumbbell.handle_radius_m) if dumbbell is not None else 0.0
    return np.asarray(platform.xyz_m, float) + np.array([0.0, 0.0, top + below + release_height])


# ---------------------------------------------------------------------------------------------
# Constraint evaluation (our own, used by the solver and to check its answer)
# ---------------------------------------------------------------------------------------------
class TaskConstraints:
    """Values and Jacobians in y = [Z.ravel(), q_goal] of every constraint of one problem."""

    def __init__(self, problem: TaskProblem):
        from .planner import _floor_exempt  # the base stands on the floor

        self.p = problem
        st = problem.settings
        robot = problem.robot
        self.n = robot.n
        self.param = Parametrization.make(st.num_pieces)
        self.piece = st.duration_s / st.num_pieces
        jp = robot.joint_params
        tb = problem.tracking
        self.q_lo = jp.position_lower + tb.position
        self.q_hi = jp.position_upper - tb.position
        self.v_max = jp.velocity_limit - tb.velocity
        self.tau_max = (1.0 - st.torque_margin_ratio) * jp.torque_limit
        # Collision samples: midpoints of equal windows tiling each piece; on a window the curve
        # stays in the hull of its restricted control points (window_matrix @ X).
        per_piece = -(-st.collision_samples // st.num_pieces)
        edges = np.linspace(0.0, 1.0, per_piece + 1)
        self.t_col = np.concatenate([(p + 0.5 * (edges[:-1] + edges[1:])) * self.piece for p in range(st.num_pieces)])
        self.col_basis = self._pair(basis(self.t_col, st.num_pieces, self.piece))
        self.window_matrix = np.zeros((len(self.t_col), 6, 6 * st.num_pieces))
        for p in range(st.num_pieces):
            for w, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
                self.window_matrix[p * per_piece + w, :, 6 * p : 6 * p + 6] = restriction_matrix(DEGREE, a, b)
        self.lipschitz = reach.sphere_lipschitz(robot.tree, problem.spheres)
        self.floor_exempt = _floor_exempt(robot.tree, problem.spheres)
        self.t_tau = np.linspace(0.0, st.duration_s, st.torque_samples)
        self.tau_basis = [self._pair(basis(self.t_tau, st.num_pieces, self.piece, k)) for k in range(3)]
        self._cache = {}

    def _remember(self, key, value):
        """Cache of the last evaluations (a solver asks for values and gradients at one point
        through several constraints)."""
        if len(self._cache) > 16:
            self._cache.clear()
        self._cache[key] = value
        return value

    def _pair(self, b):
        """(B N, B g_start, B g_goal): sample rows in terms of Z, q_start, q_goal."""
        return b @ self.param.null, b @ self.param.g_start, b @ self.param.g_goal

    @property
    def num_vars(self):
        return self.param.r * self.n + self.n

    def split(self, y):
        y = np.asarray(y, float)
        return y[: -self.n].reshape(self.param.r, self.n), y[-self.n :]

    def control_points(self, y):
        z, q_goal = self.split(y)
        return self.param.control_points(z, self.p.q_start, q_goal)

    def trajectory(self, y):
        return PiecewiseBezier(self.control_points(y).reshape(-1, 6, self.n), self.piece)

    def _samples(self, pair, y):
        bn, bs, bg = pair
        z, q_goal = self.split(y)
        return bn @ z + np.outer(bs, self.p.q_start) + np.outer(bg, q_goal)

    def _chain(self, d, pair):
        """d (G, N, n): derivatives w.r.t. the sampled joint values -> (G, num_vars)."""
        bn, _, bg = pair
        dz = np.einsum("gij,ir->grj", d, bn).reshape(d.shape[0], -1)
        return np.concatenate([dz, np.einsum("gij,i->gj", d, bg)], 1)

    # -- linear: hull constraints on control points (per joint) ------------------------------
    def hull_rows(self):
        """[(A (rows, r + 1), const (rows,), lo, hi, joint)] with A [Z[:, j]; q_goal_j] + const in [lo, hi]."""
        par = self.param
        a = np.concatenate([par.null, par.g_goal[:, None]], 1)
        m = a.shape[0]
        diff = np.kron(np.eye(self.p.settings.num_pieces), _difference(np.eye(6), 1)) / self.piece  # velocity points
        out = []
        for j in range(self.n):
            const = par.g_start * self.p.q_start[j]
            if np.isfinite(self.q_lo[j]) or np.isfinite(self.q_hi[j]):
                out.append((a, const, np.full(m, self.q_lo[j]), np.full(m, self.q_hi[j]), j))
            out.append(
                (
                    diff @ a,
                    diff @ const,
                    np.full(diff.shape[0], -self.v_max[j]),
                    np.full(diff.shape[0], self.v_max[j]),
                    j,
                )
            )
        return out

    def hull_violation(self, y):
        z, q_goal = self.split(y)
        worst = 0.0
        for a, const, lo, hi, j in self.hull_rows():
            val = a @ np.concatenate([z[:, j], [q_goal[j]]]) + const
            worst = max(worst, float(np.max(lo - val)), float(np.max(val - hi)))
        return worst

    def cost_matrices(self):
        """Per joint: (Q, b, c) with cost_j = 0.5 w^T Q w + b^T w + c, w = [Z[:, j], q_goal_j]."""
        par = self.param
        gram = jerk_gram(self.p.settings.num_pieces, self.piece)
        a = np.concatenate([par.null, par.g_goal[:, None]], 1)
        out = []
        for j in range(self.n):
            const = par.g_start * self.p.q_start[j]
            out.append((2 * a.T @ gram @ a, 2 * a.T @ gram @ const, float(const @ gram @ const)))
        return out

    def cost(self, y):
        x = self.control_points(y)
        return float(np.einsum("ij,ik,kj->", x, jerk_gram(self.p.settings.num_pieces, self.piece), x))

    # -- collision ---------------------------------------------------------------------------
    def spread(self, y):
        """(N, m): bound of how far each sphere moves on its window, the tube included."""
        q = self._samples(self.col_basis, y)
        _, dc = reach.sphere_centres(self.p.robot.tree, self.p.spheres, q)
        rho = self.window_radius(y, q)
        return reach.local_spread(self.p.robot.tree, self.lipschitz, np.linalg.norm(dc, axis=-1), rho, rho)

    def collision_pairs(self, y, with_jacobian=True, spread=None):
        """vals (O, N, m) = sd - radius - spread per (obstacle incl. floor last, sample, sphere),
        and d vals / d q_samples (O, N, m, n). spread: fixed margins (N, m) (a solver round) or
        None: the exact ones of y (the check)."""
        key = ("col", np.asarray(y, float).tobytes(), with_jacobian, None if spread is None else hash(spread.tobytes()))
        if key not in self._cache:
            q = self._samples(self.col_basis, y)
            self._remember(key, self._clearance(q, self.spread(y) if spread is None else spread, with_jacobian))
        return self._cache[key]

    def _clearance(self, q, spread, with_jacobian=True):
        p = self.p
        c, dc = reach.sphere_centres(p.robot.tree, p.spheres, q)
        need = p.spheres.radius[None, :] + spread
        nsamp, m = need.shape
        vals, grads = [], []
        flat = c.reshape(-1, 3)
        for o in range(len(p.boxes)):
            sd, g = reach.box_signed_distance(
                flat,
                np.broadcast_to(p.boxes.centre[o], flat.shape),
                np.broadcast_to(p.boxes.rotation[o], (len(flat), 3, 3)),
                np.broadcast_to(p.boxes.half_size[o], flat.shape),
            )
            vals.append(sd.reshape(nsamp, m) - need)
            grads.append(g.reshape(nsamp, m, 3))
        if p.floor_z is not None:
            vals.append(np.where(self.floor_exempt[None, :], np.inf, c[..., 2] - p.floor_z - need))
            grads.append(np.broadcast_to(np.array([0.0, 0.0, 1.0]), (nsamp, m, 3)))
        vals = np.stack(vals) if vals else np.zeros((0, nsamp, m))
        jac = np.einsum("osmk,smjk->osmj", np.stack(grads), dc) if (with_jacobian and len(vals)) else None
        return vals, jac

    def rest_clearance(self, q):
        """(min of sd - radius - spread, what) holding still at q inside the tube: a start or goal
        that fails this cannot be the end of any feasible trajectory."""
        q = np.atleast_2d(q)
        _, dc = reach.sphere_centres(self.p.robot.tree, self.p.spheres, q)
        rho = np.broadcast_to(self.p.tracking.position, q.shape)
        spread = reach.local_spread(self.p.robot.tree, self.lipschitz, np.linalg.norm(dc, axis=-1), rho, rho)
        vals, _ = self._clearance(q, spread, with_jacobian=False)
        if not vals.size:
            return np.inf, ""
        o, _, s = np.unravel_index(np.argmin(vals), vals.shape)
        what = "the floor" if o == len(self.p.boxes) else f"obstacle {self.p.boxes.names[o]!r}"
        return float(vals.min()), f"sphere {self.p.spheres.names[s]!r} vs {what}"

    def window_radius(self, y, q_mid):
        """(N, n) bound of |q(t) - q(t_i)| on window i (hull of the restricted control points,
        exact for this y) plus the tube's position bound: where the real arm can be."""
        pts = self.window_matrix @ self.control_points(y)  # (N, 6, n)
        dev = np.abs(pts - q_mid[:, None, :]).max(1)
        return (dev + self.p.tracking.position[None, :]) * (1 + 1e-12)

    def collision_grouped(self, y, spread):
        """Soft-min over samples per (obstacle, sphere) (<= the true min) and its Jacobian in y,
        with fixed margins `spread` (exact derivatives of a smooth function)."""
        vals, jac = self.collision_pairs(y, spread=spread)
        o, nsamp, m = vals.shape
        v = np.transpose(vals, (0, 2, 1)).reshape(o * m, nsamp)  # groups x samples
        keep = np.isfinite(v).all(1)
        v = v[keep]
        d = np.transpose(jac, (0, 2, 1, 3)).reshape(o * m, nsamp, self.n)[keep]
        vmin = v.min(1, keepdims=True)
        e = np.exp(-SOFTMIN_SHARPNESS_PER_M * (v - vmin))
        total = e.sum(1, keepdims=True)
        soft = vmin[:, 0] - np.log(total[:, 0]) / SOFTMIN_SHARPNESS_PER_M
        w = e / total
        return soft, self._chain(w[..., None] * d, self.col_basis)

    # -- torque ------------------------------------------------------------------------------
    def torque(self, y, with_jacobian=True, step=1e-6):
        """tau / limit (N, n) at the torque samples and d/dy ((N n), num_vars) (forward
        differences of the regressor inverse dynamics in (q, v, a), exact in a: tau is affine in a)."""
        key = ("tau", np.asarray(y, float).tobytes(), with_jacobian)
        if key in self._cache:
            return self._cache[key]
        p = self.p
        q, v, a = (self._samples(b, y) for b in self.tau_basis)
        nsamp, n = q.shape
        if not with_jacobian:
            return self._remember(key, (p.robot.inverse_dynamics(q, v, a, p.theta) / self.tau_max, None))
        eye = np.eye(n) * step
        qs = np.concatenate([q] + [q + e for e in eye] + [q] * (2 * n))
        vs = np.concatenate([v] * (n + 1) + [v + e for e in eye] + [v] * n)
        as_ = np.concatenate([a] * (2 * n + 1) + [a + e for e in eye])
        tau = p.robot.inverse_dynamics(qs, vs, as_, p.theta).reshape(3 * n + 1, nsamp, n)
        base = tau[0]
        deriv = (tau[1:] - base[None]) / step  # (3n, N, n_out): [d/dq_j, d/dv_j, d/da_j]
        scale = 1.0 / self.tau_max
        jac = np.zeros((nsamp * n, self.num_vars))
        for k, pair in enumerate(self.tau_basis):
            d = np.transpose(deriv[k * n : (k + 1) * n], (1, 2, 0)) * scale[None, :, None]  # (N, n_out, n_in)
            # group index = (sample, output joint); chain over the sample's input joints
            dd = np.zeros((nsamp * n, nsamp, n))
            dd[np.arange(nsamp * n), np.repeat(np.arange(nsamp), n)] = d.reshape(nsamp * n, n)
            jac += self._chain(dd, pair)
        return self._remember(key, (base * scale[None, :], jac))

    # -- placement ---------------------------------------------------------------------------
    def placement(self, q_goal, with_jacobian=True):
        """[grasp point - target (3), 1 - (gripper axis)_z] and d/d q_goal (4, n)."""
        c, dc = reach.sphere_centres(self.p.robot.tree, self._grasp_points(), np.atleast_2d(q_goal))
        vals = np.concatenate([c[0, 0] - self.p.place_xyz, [1.0 - (c[0, 1, 2] - c[0, 0, 2])]])
        if not with_jacobian:
            return vals, None
        return vals, np.concatenate([dc[0, 0].T, -(dc[0, 1, :, 2] - dc[0, 0, :, 2])[None]])

    def _grasp_points(self):
        """Two end-effector points: the grasp point and one 1 m further along the gripper's z."""
        robot = self.p.robot
        g = np.asarray(robot.extra["grasp_point"], float)
        return reach.Spheres(
            np.full(2, robot.end_effector), np.stack([g, g + [0.0, 0.0, 1.0]]), np.zeros(2), ["grasp", "axis"]
        )

    # -- everything at once ------------------------------------------------------------------
    def check(self, y):
        """Our own verdict at y: max violation over every constraint (>= 0), min sphere clearance
        and max torque ratio (w.r.t. the real limit)."""
        vals, _ = self.collision_pairs(y, with_jacobian=False)
        clearance = float(np.min(vals)) if vals.size else np.inf
        ratio, _ = self.torque(y, with_jacobian=False)
        torque_ratio = float(np.max(np.abs(ratio))) * (1.0 - self.p.settings.torque_margin_ratio)
        viol = [self.hull_violation(y), -clearance, float(np.max(np.abs(ratio))) - 1.0]
        if self.p.place_xyz is not None:
            pl, _ = self.placement(self.split(y)[1], with_jacobian=False)
            viol += [float(np.max(np.abs(pl[:3]))) - PLACEMENT_TOL_M, pl[3] - (1 - np.cos(GRIPPER_TILT_TOL_RAD))]
        else:
            viol.append(float(np.max(np.abs(self.split(y)[1] - self.p.goal_q))))
        return max(0.0, max(viol)), clearance, torque_ratio

    def initial_guess(self, q_goal):
        """Unconstrained minimum-jerk Z for the given goal (a straight line in joint space)."""
        y = np.zeros(self.num_vars)
        y[-self.n :] = q_goal
        for j, (qm, b, _) in enumerate(self.cost_matrices()):
            r = self.param.r
            rhs = -(b[:r] + qm[:r, r] * q_goal[j])
            y[j : r * self.n : self.n] = np.linalg.solve(qm[:r, :r], rhs)
        return y


# ---------------------------------------------------------------------------------------------
# Inverse kinematics of a placement (Drake)
# ---------------------------------------------------------------------------------------------
def solve_placement_ik(problem: TaskProblem, q_guess=None):
    """Goal configuration for problem.place_xyz nearest to q_start, gripper vertical (Drake
    InverseKinematics). Returns (q or None, message)."""
    from pydrake.multibody.inverse_kinematics import InverseKinematics
    from pydrake.solvers import Solve

    from .robot_model import make_plant

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
def solve_task_trajectory(problem: TaskProblem, solver=None, fallback=True) -> TaskResult:
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


def certified_torque_ratio(
    problem: TaskProblem, trajectory: PiecewiseBezier, theta0, theta_lo, theta_hi, windows_per_piece=100
):
    """max_j sup |u_j| / limit_j of the ARMOUR command while tracking `trajectory`: over every
    instant (windows tiling each piece, Bézier hulls of q, dq, ddq), every tracking error in the
    tube and every theta in [theta_lo, theta_hi] (reachability's interval passivity regressor and
    robust-term bound, as the planner certifies its plans). <= 1: the controller's certificate
    covers the task trajectory with that parameter box. Returns (ratio, per-joint sup |u| (n,))."""
    from .intervals import Interval, _down, _up

    tb = problem.tracking
    edges = np.linspace(0.0, 1.0, windows_per_piece + 1)
    hulls = []
    for order in range(3):
        lo, hi = [], []
        for pts in trajectory.control_points:
            d = _difference(pts, order) / trajectory.piece_duration**order
            sub = np.stack([restriction_matrix(DEGREE - order, a, b) @ d for a, b in zip(edges[:-1], edges[1:])])
            lo.append(sub.min(1))
            hi.append(sub.max(1))
        hulls.append((np.concatenate(lo), np.concatenate(hi)))
    (q_lo, q_hi), (v_lo, v_hi), (a_lo, a_hi) = hulls

    def pad(lo, hi, r):  # outward, as reachability.PlanReach.state_boxes
        return Interval(_down(_down(lo - r) - 1e-12 * np.abs(lo)), _up(_up(hi + r) + 1e-12 * np.abs(hi)))

    q_box = pad(q_lo, q_hi, tb.position)
    wp = reach.interval_passivity_regressor(
        problem.robot, q_box, pad(v_lo, v_hi, tb.velocity), pad(v_lo, v_hi, tb.qd_a), pad(a_lo, a_hi, tb.qdd_a)
    )
    # The robust input may exceed |w_bar| on the tube (h < 0): the same excess the planner adds.
    excess = reach.barrier_excess(problem.robot, q_box, theta_lo, theta_hi, tb)
    sup, _, _ = reach.torque_bound(wp, theta0, theta_lo, theta_hi, excess)
    per_joint = sup.max(0)
    return float(np.max(per_joint / problem.robot.joint_params.torque_limit)), per_joint


# ---------------------------------------------------------------------------------------------
# Cache: one JSON file per problem, keyed by a hash of everything the result depends on
# ---------------------------------------------------------------------------------------------
def cache_key(problem: TaskProblem, solver=None, fallback=True):
    """sha256 of every input: model files' contents (URDF, parameter file, sphere file), the
    model arrays, payload, obstacles, floor, start, goal, tube, settings, solver, VERSION."""
    robot = problem.robot
    doc = robot.extra.get("params_doc") or {}
    files = [Path(robot.source)] + (
        [Path(robot.source).parent / doc["planner_spheres"]] if doc.get("planner_spheres") else []
    )
    jp = robot.joint_params
    inputs = {
        "version": VERSION,
        "files": {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in files},
        "params_doc": doc,
        "joint_params": {
            k: getattr(jp, k)
            for k in (
                "names",
                "position_lower",
                "position_upper",
                "velocity_limit",
                "torque_limit",
                "coulomb",
                "viscous",
                "armature",
                "offset",
            )
        },
        "robot_theta": robot.theta,
        "coulomb_smoothing": robot.coulomb_smoothing,
        "end_effector": robot.end_effector,
        "grasp_point": robot.extra.get("grasp_point"),
        "theta": problem.theta,
        "dumbbell": None if problem.dumbbell is None else problem.dumbbell.__dict__,
        "obstacles": [[o.name, list(o.xyz_m), list(o.rpy_rad), list(o.size_m)] for o in problem.obstacles],
        "floor_z": problem.floor_z,
        "q_start": problem.q_start,
        "goal_q": problem.goal_q,
        "place_xyz": problem.place_xyz,
        "tracking": problem.tracking.__dict__,
        "settings": problem.settings.__dict__,
        "solver": solver or problem.settings.solver,
        "fallback": fallback,
    }
    text = json.dumps(_jsonable(inputs), sort_keys=True, default=float)
    return hashlib.sha256(text.encode()).hexdigest()


def task_trajectory_cached(problem, cache_dir, solver=None, fallback=True) -> TaskResult:
    """solve_task_trajectory through a cache: `cache_dir`/task_<key>.json holds the result for
    the inputs hashed by cache_key; a hit loads it without solving (details['cache'] = 'hit'),
    a miss solves and stores (solver errors are not stored). `problem`: a TaskProblem or a
    scenario with a task section."""
    if not isinstance(problem, TaskProblem):
        problem = task_problem_from_scenario(problem)
    key = cache_key(problem, solver, fallback)
    path = Path(cache_dir) / f"task_{key[:24]}.json"
    if path.is_file():
        try:
            doc = json.loads(path.read_text())
            if doc.get("key") == key:
                res = TaskResult.from_dict(doc["result"])
                res.details.update(cache="hit", cache_file=str(path))
                return res
        except (OSError, ValueError, KeyError, TypeError):
            pass  # unreadable or foreign file: recompute and overwrite
    res = solve_task_trajectory(problem, solver, fallback)
    if res.status != "solver_failed":
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"key": key, "version": VERSION, "result": res.to_dict()}, indent=1))
        tmp.replace(path)  # atomic: a concurrent reader never sees half a file
    res.details.update(cache="miss", cache_file=str(path))
    return res


# ---------------------------------------------------------------------------------------------
# Independent verification (the referee's geometry and Drake's dynamics)
# ---------------------------------------------------------------------------------------------
@dataclass
class TaskVerification:
    ok: bool  # no contact with obstacles/floor, limits respected with the stated margins
    min_clearance_m: float  # Drake signed distance, link shapes + payload vs obstacles + floor
    closest_pair: tuple
    max_torque_ratio: float  # max |tau_j| / limit_j, Drake inverse dynamics + joint friction
    max_velocity_ratio: float  # max |v_j| / limit_j
    max_joint_limit_ratio: float  # safety_monitor.limit_ratio (1 = at a limit)
    placement_error_m: float  # |payload centre at the end - target| (nan for a joint goal)
    gripper_tilt_rad: float  # angle of the gripper axis from vertical at the end
    num_samples: int
    failures: list = field(default_factory=list)

    def to_dict(self):
        return _jsonable(self.__dict__)


def verify_task_trajectory(problem: TaskProblem, trajectory: PiecewiseBezier, rate_hz=1000.0) -> TaskVerification:
    """Re-check a trajectory at `rate_hz` with what the closed-loop referee uses: the real arm's
    scene (systems/real_arm.py: link shapes, the payload's cylinders, obstacles, floor) queried
    by SafetyMonitor.min_clearance, and Drake's CalcInverseDynamics on that plant (rotor inertia
    = armature, the payload model) plus the plant's joint friction law. Nothing here uses the
    planner spheres or the regressors. Pass/fail against the margins the optimizer claims: no
    contact; velocity <= limit - tube velocity bound; position within limits - tube position
    bound; torque <= limit (the margin ratio is claimed at the optimizer's torque samples only,
    so the dense check asks for the limit itself and reports the ratio)."""
    from pydrake.multibody.tree import MultibodyForces
    from pydrake.systems.framework import DiagramBuilder

    from .config import Planner, Scenario
    from .real_arm import add_real_arm
    from .regressors import coulomb_shape
    from .safety_monitor import SafetyMonitor, limit_ratio

    robot = problem.robot
    jp = robot.joint_params
    tb = problem.tracking
    builder = DiagramBuilder()
    scene = Scenario(
        obstacles=list(problem.obstacles),
        planner=Planner(floor_z_m=problem.floor_z if problem.floor_z is not None else -100.0),
    )
    arm = add_real_arm(builder, scene, robot=robot, dumbbell=problem.dumbbell)
    monitor = builder.AddSystem(SafetyMonitor(arm.plant, arm.scene_graph, robot, period_s=1.0))
    diagram = builder.Build()
    root = diagram.CreateDefaultContext()
    plant = arm.plant
    pctx = plant.GetMyMutableContextFromRoot(root)
    sg_ctx = arm.scene_graph.GetMyContextFromRoot(root)
    t = np.linspace(0.0, trajectory.duration, int(round(trajectory.duration * rate_hz)) + 1)
    q, v, a = trajectory.evaluate(t, orders=2)
    clearance, pair, tau = np.inf, None, np.zeros_like(q)
    forces = MultibodyForces(plant)
    friction = lambda vel: jp.coulomb * coulomb_shape(vel, robot.coulomb_smoothing) + jp.viscous * vel + jp.offset  # noqa: E731
    for k in range(len(t)):
        plant.SetPositions(pctx, arm.instance, q[k])
        plant.SetVelocities(pctx, arm.instance, v[k])
        d, p = monitor.min_clearance(arm.scene_graph.get_query_output_port().Eval(sg_ctx))
        if d < clearance:
            clearance, pair = d, p
        plant.CalcForceElementsContribution(pctx, forces)
        tau[k] = plant.CalcInverseDynamics(pctx, a[k], forces) + friction(v[k])
    torque_ratio = float(np.max(np.abs(tau) / jp.torque_limit))
    vel_ratio = float(np.max(np.abs(v) / jp.velocity_limit))
    joint_ratio = float(np.max(limit_ratio(q, jp.position_lower, jp.position_upper)))
    ee = plant.GetBodyByName(robot.body_names[robot.end_effector]).body_frame()
    plant.SetPositions(pctx, arm.instance, q[-1])
    pose = plant.CalcRelativeTransform(pctx, plant.world_frame(), ee)
    tilt = float(np.arccos(np.clip(pose.rotation().matrix()[2, 2], -1.0, 1.0)))
    place_err = float("nan")
    if problem.place_xyz is not None:
        place_err = float(np.linalg.norm(pose @ np.asarray(robot.extra["grasp_point"], float) - problem.place_xyz))
    failures = []
    if clearance <= 0:
        failures.append(f"contact: clearance {clearance:.4f} m ({pair})")
    if np.any(np.abs(v) > jp.velocity_limit - tb.velocity + 1e-9):
        failures.append("velocity above limit - tube bound")
    if np.any(q < jp.position_lower + tb.position - 1e-9) or np.any(q > jp.position_upper - tb.position + 1e-9):
        failures.append("position outside limits - tube bound")
    if torque_ratio > 1:
        failures.append(f"torque ratio {torque_ratio:.3f} > 1")
    if (
        np.max(np.abs(v[[0, -1]])) > 1e-9
        or np.max(np.abs(a[[0, -1]])) > 1e-9
        or np.max(np.abs(q[0] - problem.q_start)) > 1e-9
    ):
        failures.append("does not start at q_start at rest or does not end at rest")
    if problem.place_xyz is not None and (
        place_err > PLACEMENT_TOL_M * np.sqrt(3) + 1e-9 or tilt > GRIPPER_TILT_TOL_RAD
    ):
        failures.append(f"placement error {place_err:.4g} m, gripper tilt {tilt:.3g} rad")
    if problem.goal_q is not None and np.max(np.abs(q[-1] - problem.goal_q)) > 1e-6:
        failures.append("does not end at goal_q")
    return TaskVerification(
        not failures, float(clearance), pair, torque_ratio, vel_ratio, joint_ratio, place_err, tilt, len(t), failures
    )
