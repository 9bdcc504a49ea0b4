"""One planning problem of the safe planner (paper §VI): for one call, everything that does not
depend on k precomputed once, then its constraints, costs and certificate as functions of k (numpy,
vectorized). The solver loop that uses them is safe_planner.SafePlanner.

- joint position / velocity limits -> a box of k (reachability.PlanReach.limit_box, exact hull property);
- torque -> the rigorous interval-RNEA check over the whole k box (torque_box.py, the box shrunk if needed);
- collision -> one smooth constraint per (time interval, sphere, obstacle) pair that can be active,
  sd(c_s(q_mid_i(k)), obstacle) >= r_s + spread_is, handed to the solver as a soft-min per (sphere,
  obstacle) and verified per pair (`is_feasible`);
- cost -> "exciting" (log cond of the stacked end-effector regressor W_e(k), exact gradient) or "goal".
"""

from __future__ import annotations

from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.math.bezier import QuinticBezier, restriction_matrix
from safesysid.systems.math.intervals import dot_rounding
from safesysid.systems.planner import reachability as reach
from safesysid.systems.planner.ee_regressor import ee_standard_regressor
from safesysid.systems.planner.torque_box import fit_torque_box

if TYPE_CHECKING:
    from safesysid.systems.planner.setup import PlannerSetup

# Columns of W_e (m, m c, I) the exciting cost conditions (scenario planner.exciting_columns).
_EXCITING_COLUMNS = {"all": slice(0, 10), "inertia": slice(4, 10)}

SOFTMIN_SHARPNESS_PER_M = 2000.0  # soft-min of a group <= its true min (gap <= log(count)/beta)


@lru_cache(maxsize=8)
def _restrictions(num_intervals):
    s = np.linspace(0, 1, num_intervals + 1)
    return [np.stack([restriction_matrix(5 - o, a, b) for a, b in zip(s[:-1], s[1:])]) for o in range(3)]


class PlanningProblem:
    """Constraints and costs of one planning call, as functions of k (numpy, vectorized)."""

    def __init__(
        self,
        planner: PlannerSetup,
        q0: ArrayLike,
        v0: ArrayLike,
        a0: ArrayLike,
        theta0: ArrayLike,
        theta_lo: ArrayLike,
        theta_hi: ArrayLike,
        *,
        mode: str | None = None,
        past: np.ndarray | None = None,
        k_box: tuple[np.ndarray, np.ndarray] | None = None,
        certify_torque: bool = True,
        shrink_toward: np.ndarray | None = None,
        box_scale: float = 1.0,
    ) -> None:
        self.planner = planner
        self.mode = mode or planner.config.cost
        # W_e rows of the motion executed before this plan (SafePlanner.executed_rows): the
        # exciting cost then conditions [past; W_e(k)], so a plan excites what is still missing.
        self.past = None if past is None or len(past) == 0 else np.asarray(past, float)
        # The end effector's current interval widths (floored): planner.exciting_criterion a_optimal
        # weighs each parameter's predicted variance by 1/width^2, e_optimal and cond_interval scale
        # the columns of W_e by them.
        ee_width = np.subtract(theta_hi, theta_lo, dtype=float)[planner.robot.ee_slice]
        self.interval_width = np.maximum(ee_width, 1e-6)
        self.variance_weight = 1.0 / self.interval_width**2
        cfg = planner.config
        robot = planner.robot
        self.n = robot.n
        self.reach = reach.PlanReach(
            q0,
            v0,
            a0,
            cfg.duration_s,
            planner.k_center,
            planner.k_range,
            cfg.num_time_intervals,
            planner.tracking,
            restrictions=_restrictions(cfg.num_time_intervals),
        )
        self.reason = ""
        self.feasible_start = True
        self.torque_infeasible = False  # True: no shrunk k box fits the torque limits
        k_lo, k_hi, why = self.reach.limit_box(robot.joint_params)
        if k_lo is None:
            self._fail(why)
            return
        if box_scale < 1.0:  # the limit box shrunk toward k = 0 (its nearest point): refinement's wide solve
            base = np.clip(np.zeros(self.n), k_lo, k_hi)
            k_lo, k_hi = base + box_scale * (k_lo - base), base + box_scale * (k_hi - base)
        if k_box is not None:  # a sub-box (a point: the certificate of one plan, SafePlanner._refine)
            k_lo, k_hi = np.maximum(k_lo, k_box[0]), np.minimum(k_hi, k_box[1])
            if np.any(k_lo > k_hi):
                self._fail("the given k box is outside the joint position/velocity limits")
                return
        self.k_lo, self.k_hi = k_lo, k_hi
        self.torque_ratio = np.nan
        if certify_torque and not self._certify_torque((theta0, theta_lo, theta_hi), shrink_toward):
            return
        self._collision_pairs()
        # Exciting-cost sample instants and their end weights (dq/dq_end, dqd/dq_end, dqdd/dq_end).
        ns = cfg.num_cost_samples
        self.t_cost = np.linspace(0.0, cfg.duration_s, ns)
        self.w_cost = np.stack(QuinticBezier.end_weights(self.t_cost, cfg.duration_s))  # (3, ns)
        # planner.exciting_weighting noise: each row's weight, on the plan that keeps k = 0. Fixed:
        # weights that grew the wrist's noise with the candidate's own acceleration (armature)
        # held the wrist still, and identified less (README, "Tried and no better").
        self.row_weight = None
        if planner.weighs_rows:
            still = self.desired_at(self.t_cost, np.clip(np.zeros(self.n), self.k_lo, self.k_hi))
            self.row_weight = planner.row_weights(*still, theta0)
        self._cache = {}
        self._excite_cache = {}

    def _fail(self, why):
        self.feasible_start = False
        self.reason = why

    def _certify_torque(self, theta, shrink_toward):
        """Shrink the k box to the largest one whose rigorous torque bound fits the limits
        (torque_box.py; toward k = 0, or toward shrink_toward when given); False if none does."""
        centre = np.clip(np.zeros(self.n), self.k_lo, self.k_hi) if shrink_toward is None else shrink_toward
        fit = fit_torque_box(self.planner, self.reach, (self.k_lo, self.k_hi), theta=theta, centre=centre)
        if fit.k_lo is None:
            self.torque_infeasible = True
            self._fail(fit.why)
            return False
        self.k_lo, self.k_hi, self.torque_ratio = fit.k_lo, fit.k_hi, fit.ratio
        return True

    # -- collision pairs -------------------------------------------------------------------------
    def _collision_pairs(self):
        pl = self.planner
        spheres, lips = pl.spheres, pl.lipschitz
        r = self.reach
        k_mid = 0.5 * (self.k_lo + self.k_hi)
        k_half = 0.5 * (self.k_hi - self.k_lo)
        c, jac = reach.sphere_centres(pl.robot.tree, spheres, r.q_mid(k_mid))
        k_dev = np.abs(r.w_mid)[:, None] * (r.kr * k_half)[None, :]  # |q_mid(k) - q_mid(k_mid)|
        self.spread = reach.local_spread(
            pl.robot.tree, lips, np.linalg.norm(jac, axis=-1), rho=r.rho, reach_radius=r.rho + k_dev
        )
        # Centre motion over the whole k box (Lipschitz): used to drop pairs no k can activate.
        k_motion = k_dev @ lips.T  # (nint, m)
        need = spheres.radius[None, :] + self.spread  # required clearance of the centre
        nint, m = self.spread.shape
        ii, ss = np.meshgrid(np.arange(nint), np.arange(m), indexing="ij")
        clearances = []  # (centre signed distance (nint, m), obstacle index; -1: the floor)
        boxes = pl.boxes
        for o in range(len(boxes)):
            sd, _ = reach.box_signed_distance(
                c.reshape(-1, 3),
                np.broadcast_to(boxes.centre[o], (nint * m, 3)),
                np.broadcast_to(boxes.rotation[o], (nint * m, 3, 3)),
                np.broadcast_to(boxes.half_size[o], (nint * m, 3)),
            )
            clearances.append((sd.reshape(nint, m), o))
        if pl.floor_z is not None:
            clearances.append((np.where(pl.floor_exempt[None, :], np.inf, c[..., 2] - pl.floor_z), -1))
        pairs_i, pairs_s, pairs_o = [], [], []
        # The least clearance over EVERY pair at the box centre (a point problem's own k, whose kept
        # pairs are only those within 1 mm of their margin, often none): what a refined plan reports.
        self.centre_clearance = min((float((sd - need).min()) for sd, _ in clearances), default=np.inf)
        for sd, o in clearances:
            self._check_start(sd, need, k_motion, o)
            keep = sd - k_motion - need < 1e-3
            pairs_i.append(ii[keep]), pairs_s.append(ss[keep]), pairs_o.append(np.full(keep.sum(), o))
        self.pair_i = np.concatenate(pairs_i) if pairs_i else np.zeros(0, int)
        self.pair_s = np.concatenate(pairs_s) if pairs_s else np.zeros(0, int)
        self.pair_o = np.concatenate(pairs_o) if pairs_o else np.zeros(0, int)
        # Solver constraints: one soft-min per (sphere, obstacle) over its time intervals.
        group_key = self.pair_s * (len(pl.boxes) + 1) + (self.pair_o + 1)
        order = np.argsort(group_key, kind="stable")
        self.pair_i, self.pair_s, self.pair_o = self.pair_i[order], self.pair_s[order], self.pair_o[order]
        _, self.group_start, self.group_of_pair = np.unique(group_key[order], return_index=True, return_inverse=True)
        self.pair_need = need[self.pair_i, self.pair_s]
        self.active_intervals = np.unique(self.pair_i)

    def _check_start(self, sd, need, k_motion, o):
        """A pair violated for EVERY k of the box (e.g. the start is inside a margin) -> infeasible."""
        if not self.feasible_start:
            return
        hopeless = sd + k_motion - need < 0
        if np.any(hopeless):
            i, s = np.argwhere(hopeless)[0]
            what = "the floor" if o < 0 else f"obstacle {self.planner.boxes.names[o]!r}"
            self._fail(
                f"sphere {self.planner.spheres.names[s]!r} cannot clear {what} at t = "
                f"{self.reach.t_mid[i]:.2f} s for any k (start inside the safety margin)"
            )

    @property
    def num_constraints(self) -> int:
        """Number of solver constraints (soft-min groups)."""
        return len(self.group_start)

    @property
    def num_pairs(self) -> int:
        """Number of (interval, sphere, obstacle) constraints checked rigorously."""
        return len(self.pair_i)

    def collision_grouped(self, k: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Soft-min per group, -log(sum exp(-beta g))/beta <= min g: >= 0 implies every pair >= 0."""
        vals, jac = self.collision(k)
        if len(vals) == 0:
            return vals, jac
        beta = SOFTMIN_SHARPNESS_PER_M
        gmin = np.minimum.reduceat(vals, self.group_start)
        e = np.exp(-beta * (vals - gmin[self.group_of_pair]))
        total = np.add.reduceat(e, self.group_start)
        soft = gmin - np.log(total) / beta
        weights = e / total[self.group_of_pair]
        return soft, np.add.reduceat(weights[:, None] * jac, self.group_start, axis=0)

    def collision(self, k: ArrayLike, with_jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Constraint values (P,) >= 0 means safe (up to their rounding: `is_feasible`), and d/dk (P, n)."""
        vals, jac, _ = self._pair_values(k, with_jacobian)
        return vals, jac

    def _pair_values(self, k, with_jacobian):
        """(values, d/dk, sphere centres (P, 3)) of the kept pairs at k."""
        k = np.asarray(k, float)
        if len(self.pair_i) == 0:
            return np.zeros(0), np.zeros((0, self.n)), np.zeros((0, 3))
        pl = self.planner
        r = self.reach
        ints = self.active_intervals
        qm = r.q_mid(k)[ints]
        c, dc = reach.sphere_centres(pl.robot.tree, pl.spheres, qm, with_jacobian=with_jacobian)
        pos = np.searchsorted(ints, self.pair_i)
        pts = c[pos, self.pair_s]
        vals = np.empty(len(pts))
        grad = np.empty((len(pts), 3))
        box = self.pair_o >= 0
        if np.any(box):
            o = self.pair_o[box]
            sd, g = reach.box_signed_distance(pts[box], pl.boxes.centre[o], pl.boxes.rotation[o], pl.boxes.half_size[o])
            vals[box], grad[box] = sd, g
        floor = ~box
        vals[floor] = pts[floor, 2] - pl.floor_z
        grad[floor] = (0.0, 0.0, 1.0)
        vals = vals - self.pair_need
        if not with_jacobian:
            return vals, None, pts
        dcdq = dc[pos, self.pair_s]  # (P, n, 3)
        dqdk = r.w_mid[self.pair_i][:, None] * r.kr[None, :]  # (P, n)
        jac = (dcdq @ grad[..., None])[..., 0] * dqdk
        return vals, jac, pts

    def is_feasible(self, k: ArrayLike) -> bool:
        """k in the box and every kept pair's float clearance above what its rounding may add."""
        k = np.asarray(k, float)
        if np.any(k < self.k_lo) or np.any(k > self.k_hi):
            return False
        vals, _, pts = self._pair_values(k, with_jacobian=False)
        return bool(np.all(vals >= self.clearance_rounding(pts)))

    def clearance_rounding(self, pts: np.ndarray) -> np.ndarray:
        """(P,) bound on how far each float clearance may exceed the exact one: box_signed_distance
        rounds p - c, a 3-term rotation, |.| - h and a 3-term norm, then the need is subtracted (the
        floor: z - floor - need), at most 8 roundings of these magnitudes (dot_rounding(8))."""
        pl = self.planner
        mag = np.abs(pts).sum(1) + self.pair_need
        box = self.pair_o >= 0
        o = self.pair_o[box]
        mag[box] += np.abs(pl.boxes.centre[o]).sum(1) + np.abs(pl.boxes.half_size[o]).sum(1)
        if pl.floor_z is not None:
            mag[~box] += abs(pl.floor_z)
        return dot_rounding(8) * mag

    # -- costs -----------------------------------------------------------------------------------
    def desired_at(self, t: ArrayLike, k: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.reach.bezier.evaluate(t, self.reach.q_end(k))

    def exciting_cost(self, k: ArrayLike) -> tuple[float, np.ndarray, np.ndarray]:
        """(log sigma_max - log sigma_min of W_e(k) stacked over the cost samples, below the past
        motion's rows when given, rows weighted when planner.exciting_weighting says so; its exact
        gradient in k; the plan's own unweighted W_e(k)), cached."""
        key = np.asarray(k, float).tobytes()
        if key not in self._excite_cache:
            self._excite_cache[key] = self._exciting_cost(np.asarray(k, float))
        return self._excite_cache[key]

    def _exciting_cost(self, k):
        pl = self.planner
        n = self.n
        q, v, a = self.desired_at(self.t_cost, k)
        h = 1e-30
        ns = len(self.t_cost)
        # One complex sample per (instant, k_j): direction kr_j * (w_q, w_v, w_a)(t) e_j.
        dirs = np.zeros((n, ns, 3, n))
        for j in range(n):
            dirs[j, :, :, j] = pl.k_range[j] * self.w_cost.T
        qc = q[None] + 1j * h * dirs[:, :, 0]
        vc = v[None] + 1j * h * dirs[:, :, 1]
        ac = a[None] + 1j * h * dirs[:, :, 2]
        w = ee_standard_regressor(
            pl.robot.tree, pl.robot.end_effector, qc.reshape(-1, n), v=vc.reshape(-1, n), a=ac.reshape(-1, n)
        ).reshape(n, ns * n, 10)
        cols = _EXCITING_COLUMNS[getattr(pl.config, "exciting_columns", "all")]
        plain = W = w[0].real[:, cols]
        dW = w.imag[..., cols] / h  # (n_k, rows, columns)
        if self.row_weight is not None:
            W, dW = W * self.row_weight[:, None], dW * self.row_weight[None, :, None]
        # With the past motion stacked on top, only the plan's rows depend on k.
        stacked = W if self.past is None else np.vstack([self.past[:, cols], W])
        criterion = getattr(pl.config, "exciting_criterion", "cond")
        if criterion == "a_optimal":
            return (*self._a_optimal(stacked, W, dW, self.variance_weight[cols]), plain)
        if criterion in ("e_optimal", "cond_interval"):  # columns in units of their current interval
            width = self.interval_width[cols]
            stacked, W, dW = stacked * width, W * width, dW * width
        u, s, vt = np.linalg.svd(stacked, full_matrices=False)
        if criterion == "e_optimal" and s[-1] > 0:
            u = u[len(stacked) - len(W) :]
            d_min = np.einsum("r,jrc,c->j", u[:, -1], dW, vt[-1])
            return float(-np.log(s[-1])), -d_min / s[-1], plain
        if s[-1] <= 0:
            return np.inf, np.zeros(n), plain
        u = u[len(stacked) - len(W) :]
        if criterion == "d_optimal":  # -sum log sigma_i = -log sqrt(det S^T S): no column scale matters
            d_all = np.einsum("ri,jrc,ic->ji", u, dW, vt)
            return float(-np.sum(np.log(s))), -(d_all / s).sum(axis=1), plain
        d_max = np.einsum("r,jrc,c->j", u[:, 0], dW, vt[0])
        d_min = np.einsum("r,jrc,c->j", u[:, -1], dW, vt[-1])
        return float(np.log(s[0]) - np.log(s[-1])), d_max / s[0] - d_min / s[-1], plain

    @staticmethod
    def _a_optimal(stacked, W, dW, weight):
        """(log sum_j w_j (A^-1)_jj, its gradient), A = S^T S of the stacked rows S whose last
        rows W move with k (dW: (n_k, rows, columns)): the least-squares estimate's variance per
        parameter under unit white noise, weighted (A-optimal design). dC = -C dA C."""
        A = stacked.T @ stacked
        try:
            C = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            return np.inf, np.zeros(len(dW))
        value = float(weight @ np.diag(C))
        if not np.isfinite(value) or value <= 0:
            return np.inf, np.zeros(len(dW))
        G = C @ (weight[:, None] * C)  # d value / dA = -G
        dA = np.einsum("jrc,rd->jcd", dW, W)
        dA = dA + dA.transpose(0, 2, 1)
        return float(np.log(value)), -np.einsum("jcd,cd->j", dA, G) / value

    def goal_cost(self, k: ArrayLike) -> tuple[float, np.ndarray]:
        goal = np.asarray(self.planner.config.goal_q_rad, float)
        diff = self.reach.q_end(k) - goal
        return float(diff @ diff), 2 * diff * self.reach.kr

    def cost(self, k: ArrayLike) -> tuple[float, np.ndarray]:
        if self.mode == "goal":
            return self.goal_cost(k)
        val, grad, _ = self.exciting_cost(k)
        return val, grad

    def cond(self, k: ArrayLike) -> float:
        _, _, W = self.exciting_cost(k)
        s = np.linalg.svd(W, compute_uv=False)
        return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


# ---------------------------------------------------------------------------------------------
