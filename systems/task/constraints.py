"""Constraint evaluation of the task-trajectory optimization (systems/task/trajectory.py): our own
values and Jacobians, used by the solver and to check its answer (hull limits, collision of the
planner's spheres with the window and tube margins, nominal torque, placement)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.math.bezier import _difference, restriction_matrix
from safesysid.systems.math.piecewise_bezier import DEGREE, Parametrization, PiecewiseBezier, basis, jerk_gram
from safesysid.systems.planner import reachability as reach

SOFTMIN_SHARPNESS_PER_M = 2000.0  # soft-min <= min, gap <= log(samples) / beta (2.6 mm at 200)
PLACEMENT_TOL_M = 1e-4  # placement equality as a box of this half-width
GRIPPER_TILT_TOL_RAD = 1e-3  # gripper axis vs vertical at a placement

if TYPE_CHECKING:
    from safesysid.systems.task.problem import TaskProblem


class TaskConstraints:
    """Values and Jacobians in y = [Z.ravel(), q_goal] of every constraint of one problem."""

    def __init__(self, problem: TaskProblem):
        from safesysid.systems.planner.reachability import floor_exempt  # the base stands on the floor

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
        self.floor_exempt = floor_exempt(robot.tree, problem.spheres)
        self.t_tau = np.linspace(0.0, st.duration_s, st.torque_samples)
        self.tau_basis = [self._pair(basis(self.t_tau, st.num_pieces, self.piece, order=k)) for k in range(3)]
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
    def num_vars(self) -> int:
        return self.param.r * self.n + self.n

    def split(self, y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        y = np.asarray(y, float)
        return y[: -self.n].reshape(self.param.r, self.n), y[-self.n :]

    def control_points(self, y: ArrayLike) -> np.ndarray:
        z, q_goal = self.split(y)
        return self.param.control_points(z, self.p.q_start, q_goal)

    def trajectory(self, y: ArrayLike) -> PiecewiseBezier:
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
    def hull_rows(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]]:
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

    def hull_violation(self, y: ArrayLike) -> float:
        z, q_goal = self.split(y)
        worst = 0.0
        for a, const, lo, hi, j in self.hull_rows():
            val = a @ np.concatenate([z[:, j], [q_goal[j]]]) + const
            worst = max(worst, float(np.max(lo - val)), float(np.max(val - hi)))
        return worst

    def cost_matrices(self) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """Per joint: (Q, b, c) with cost_j = 0.5 w^T Q w + b^T w + c, w = [Z[:, j], q_goal_j]."""
        par = self.param
        gram = jerk_gram(self.p.settings.num_pieces, self.piece)
        a = np.concatenate([par.null, par.g_goal[:, None]], 1)
        out = []
        for j in range(self.n):
            const = par.g_start * self.p.q_start[j]
            out.append((2 * a.T @ gram @ a, 2 * a.T @ gram @ const, float(const @ gram @ const)))
        return out

    def cost(self, y: ArrayLike) -> float:
        x = self.control_points(y)
        return float(np.einsum("ij,ik,kj->", x, jerk_gram(self.p.settings.num_pieces, self.piece), x))

    # -- collision ---------------------------------------------------------------------------
    def spread(self, y: ArrayLike) -> np.ndarray:
        """(N, m): bound of how far each sphere moves on its window, the tube included."""
        q = self._samples(self.col_basis, y)
        _, dc = reach.sphere_centres(self.p.robot.tree, self.p.spheres, q)
        rho = self.window_radius(y, q)
        return reach.local_spread(
            self.p.robot.tree, self.lipschitz, np.linalg.norm(dc, axis=-1), rho=rho, reach_radius=rho
        )

    def collision_pairs(
        self, y: ArrayLike, with_jacobian: bool = True, spread: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray | None]:
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

    def rest_clearance(self, q: ArrayLike) -> tuple[float, str]:
        """(min of sd - radius - spread, what) holding still at q inside the tube: a start or goal
        that fails this cannot be the end of any feasible trajectory."""
        q = np.atleast_2d(q)
        _, dc = reach.sphere_centres(self.p.robot.tree, self.p.spheres, q)
        rho = np.broadcast_to(self.p.tracking.position, q.shape)
        spread = reach.local_spread(
            self.p.robot.tree, self.lipschitz, np.linalg.norm(dc, axis=-1), rho=rho, reach_radius=rho
        )
        vals, _ = self._clearance(q, spread, with_jacobian=False)
        if not vals.size:
            return np.inf, ""
        o, _, s = np.unravel_index(np.argmin(vals), vals.shape)
        what = "the floor" if o == len(self.p.boxes) else f"obstacle {self.p.boxes.names[o]!r}"
        return float(vals.min()), f"sphere {self.p.spheres.names[s]!r} vs {what}"

    def window_radius(self, y: ArrayLike, q_mid: np.ndarray) -> np.ndarray:
        """(N, n) bound of |q(t) - q(t_i)| on window i (hull of the restricted control points,
        exact for this y) plus the tube's position bound: where the real arm can be."""
        pts = self.window_matrix @ self.control_points(y)  # (N, 6, n)
        dev = np.abs(pts - q_mid[:, None, :]).max(1)
        return (dev + self.p.tracking.position[None, :]) * (1 + 1e-12)

    def collision_grouped(self, y: ArrayLike, spread: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
    def torque(
        self, y: ArrayLike, with_jacobian: bool = True, step: float = 1e-6
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """tau / limit (N, n) at the torque samples and d/dy ((N n), num_vars) (forward
        differences of the regressor inverse dynamics in (q, v, a), exact in a: tau is affine in a)."""
        key = ("tau", np.asarray(y, float).tobytes(), with_jacobian)
        if key in self._cache:
            return self._cache[key]
        p = self.p
        q, v, a = (self._samples(b, y) for b in self.tau_basis)
        nsamp, n = q.shape
        if not with_jacobian:
            return self._remember(key, (p.robot.inverse_dynamics(q, v, a, theta=p.theta) / self.tau_max, None))
        eye = np.eye(n) * step
        qs = np.concatenate([q] + [q + e for e in eye] + [q] * (2 * n))
        vs = np.concatenate([v] * (n + 1) + [v + e for e in eye] + [v] * n)
        as_ = np.concatenate([a] * (2 * n + 1) + [a + e for e in eye])
        tau = p.robot.inverse_dynamics(qs, vs, as_, theta=p.theta).reshape(3 * n + 1, nsamp, n)
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
    def placement(self, q_goal: ArrayLike, with_jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
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
    def check(self, y: ArrayLike) -> tuple[float, float, float]:
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

    def initial_guess(self, q_goal: np.ndarray) -> np.ndarray:
        """Unconstrained minimum-jerk Z for the given goal (a straight line in joint space)."""
        y = np.zeros(self.num_vars)
        y[-self.n :] = q_goal
        for j, (qm, b, _) in enumerate(self.cost_matrices()):
            r = self.param.r
            rhs = -(b[:r] + qm[:r, r] * q_goal[j])
            y[j : r * self.n : self.n] = np.linalg.solve(qm[:r, :r], rhs)
        return y
