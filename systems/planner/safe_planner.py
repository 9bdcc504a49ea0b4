"""Provably-safe exciting-trajectory planner (ARMOUR receding horizon, paper §VI). Pure math.

(Over 500 lines: one planning problem, its constraints, costs and solve loop read as one unit; the
reachability math itself lives in reachability.py, interval_dynamics.py and affine_forms.py.)

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
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.controller.armour import TrackingBounds
from safesysid.systems.math.bezier import QuinticBezier, restriction_matrix
from safesysid.systems.math.blas import single_threaded_blas
from safesysid.systems.math.intervals import Interval, dot_rounding
from safesysid.systems.math.spatial import cross, to_body
from safesysid.systems.model import regressors
from safesysid.systems.model.robot_defaults import robot_defaults
from safesysid.systems.planner import reachability as reach
from safesysid.systems.planner.affine_forms import concat_rows

if TYPE_CHECKING:
    from safesysid.systems.config import Obstacle, Planner
    from safesysid.systems.model.payload import Dumbbell
    from safesysid.systems.model.robot_model import RobotModel

COLLISION_SOLVER_MARGIN_M = 1e-4
# The plain interval bound is tried on the shrunk k boxes only when the whole box is at most this far
# over the limit (speed only: the affine bound is tried in any case, and every bound is rigorous).
PLAIN_SHRINK_RATIO = 1.6  # the solver aims this far inside; verification asks >= 0


_CAP_MESSAGE = "planner wall-time cap reached"


class _WallTimeExceeded(Exception):
    """Raised from our callbacks to stop the solver at the wall-time cap (both Ipopt and SNOPT
    unwind cleanly; the best verified-feasible evaluated point is then used)."""


# Columns of W_e (m, m c, I) the exciting cost conditions (scenario planner.exciting_columns).
_EXCITING_COLUMNS = {"all": slice(0, 10), "inertia": slice(4, 10)}

SOFTMIN_SHARPNESS_PER_M = 2000.0  # soft-min of a group <= its true min (gap <= log(count)/beta)


# ---------------------------------------------------------------------------------------------
# End-effector regressor W_e(q, qd, qdd), complex-step safe (all arithmetic analytic)
# ---------------------------------------------------------------------------------------------
# Own pass because regressors.forward_kinematics fills float buffers (the imaginary part would be
# lost). K(x) and x x* are regressors.py's, as exact gathers (reach.signed_selection): any dtype,
# and no BLAS call (a threaded one on the shared cores costs ~10 ms here).
_K_MAP = reach.signed_selection(regressors.inertia_times(np.eye(6)))
_FORCE_CROSS_MAP = reach.signed_selection(regressors.cross_force_matrix(np.eye(6)))


def _linear(x, selection, shape):
    """The linear map of `selection` applied to x (..., 6) -> (..., *shape)."""
    comp, sign = selection
    return (x[..., comp] * sign).reshape(x.shape[:-1] + shape)


def _motion_cross(v, m):
    """regressors.cross_motion on spatial.cross (np.cross's overhead: ~3 ms per W_e call here)."""
    w, u = v[..., :3], v[..., 3:]
    return np.concatenate([cross(w, m[..., :3]), cross(w, m[..., 3:]) + cross(u, m[..., :3])], -1)


def ee_standard_regressor(
    tree: regressors.KinematicTree, body: int, q: ArrayLike, v: ArrayLike, a: ArrayLike
) -> np.ndarray:
    """W_e (N, n, 10): the end-effector (body `body`) columns of the standard regressor.

    Same as RobotModel.standard_regressor(q, v, a)[..., ee_slice]; dtype-generic (complex-step).
    """
    dtype = np.result_type(q, v, a, float)
    q, v, a = (np.atleast_2d(np.asarray(x)).astype(dtype) for x in (q, v, a))
    nsamp, n = q.shape
    R = [None] * n
    p = [None] * n
    S = np.zeros((nsamp, n, 6), dtype)
    V = [None] * n
    A = [None] * n
    g = np.concatenate([np.zeros(3), -tree.gravity])
    consts = _chain_constants(tree)
    for i in range(n):
        par = tree.parent[i]
        rpj, tpj, rjc, tjc = consts[i]
        if par < 0:
            r_f = np.broadcast_to(rpj, (nsamp, 3, 3)).astype(dtype)
            p_f = np.broadcast_to(tpj, (nsamp, 3)).astype(dtype)
            v_par = np.zeros((nsamp, 6), dtype)
            a_par = np.broadcast_to(g, (nsamp, 6)).astype(dtype)
        else:
            r_f = regressors._times_const(R[par], rpj)
            p_f = p[par] + R[par] @ tpj
            v_par, a_par = V[par], A[par]
        z = r_f[..., 2]  # the joint axis is the frame's z after the constant change of basis
        if tree.prismatic[i]:
            r_m, p_m = r_f, p_f + z * q[:, i, None]
            S[:, i] = np.concatenate([np.zeros_like(z), z], -1)
        else:
            s, c = np.sin(q[:, i])[:, None], np.cos(q[:, i])[:, None]
            x_, y_ = r_f[..., 0], r_f[..., 1]
            r_m, p_m = np.stack([c * x_ + s * y_, c * y_ - s * x_, z], -1), p_f  # r_f @ Rz(q)
            S[:, i] = np.concatenate([z, cross(p_f, z)], -1)
        R[i] = regressors._times_const(r_m, rjc)
        p[i] = p_m + r_m @ tjc
        V[i] = v_par + S[:, i] * v[:, i, None]
        A[i] = a_par + S[:, i] * a[:, i, None] + _motion_cross(v_par, S[:, i]) * v[:, i, None]
    e = body
    vb = to_body(R[e], p[e], V[e])
    ab = to_body(R[e], p[e], A[e])
    anc = np.flatnonzero(tree.ancestors()[:, e])
    sb = to_body(R[e][:, None], p[e][:, None], S[:, anc])  # (N, k, 6) screws in the body frame
    y = _linear(ab, _K_MAP, (6, 10)) + _linear(vb, _FORCE_CROSS_MAP, (6, 6)) @ _linear(
        vb, _K_MAP, (6, 10)
    )  # I a + v x* I v
    out = np.zeros((nsamp, n, 10), dtype)
    out[:, anc] = sb @ y
    return out


_CHAIN = {}


def _chain_constants(tree):
    """Per joint (R_pj P, t_pj, P^T R_jc, P^T t_jc) with P a rotation taking z to the joint axis,
    so the joint rotation is a rotation about z (column arithmetic instead of a 3x3 product)."""
    key = id(tree)
    if key not in _CHAIN or _CHAIN[key][0] is not tree:
        out = []
        for i in range(tree.n):
            axis = np.asarray(tree.axis[i], float)
            rot = regressors._z_to(axis / np.linalg.norm(axis))  # columns x, y, z = axis
            xpj, xjc = tree.X_parent_joint[i], tree.X_joint_child[i]
            out.append((xpj[:3, :3] @ rot, xpj[:3, 3].copy(), rot.T @ xjc[:3, :3], rot.T @ xjc[:3, 3]))
        _CHAIN[key] = (tree, out)
    return _CHAIN[key][1]


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

    def evaluate(self, t: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Desired q, qd, qdd (each (len(t), n)) at times t since the plan's start."""
        return self.trajectory.evaluate(t, self.q_end)


# ---------------------------------------------------------------------------------------------
# One planning problem (everything that does not depend on k, precomputed once)
# ---------------------------------------------------------------------------------------------


@lru_cache(maxsize=8)
def _restrictions(num_intervals):
    s = np.linspace(0, 1, num_intervals + 1)
    return [np.stack([restriction_matrix(5 - o, a, b) for a, b in zip(s[:-1], s[1:])]) for o in range(3)]


class PlanningProblem:
    """Constraints and costs of one planning call, as functions of k (numpy, vectorized)."""

    def __init__(
        self,
        planner: SafePlanner,
        q0: ArrayLike,
        v0: ArrayLike,
        a0: ArrayLike,
        theta0: ArrayLike,
        theta_lo: ArrayLike,
        theta_hi: ArrayLike,
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
        if certify_torque and not self._torque_box(theta0, theta_lo, theta_hi, shrink_toward):
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

    # -- torque: rigorous check over the k box, shrinking it toward the centre when needed ----------
    def _torque_box(self, theta0, theta_lo, theta_hi, shrink_toward=None):
        """Largest k box (the allowed one, or shrunk toward k = 0 by halves; toward shrink_toward
        when given: on a point box, the points of the segment to it) whose rigorous torque
        bound fits the limits: plain interval bound on the whole box; if that fails, on all shrink
        levels at once (one batched call); if all fail, again with the affine (zonotope) enclosure of
        the regressor on hulls of `coarse` boxes, whose tracking error keeps its (e, r) coupling
        (interval_dynamics.affine_torque_bound: tighter, costlier)."""
        limit = self.planner.robot.joint_params.torque_limit
        robot = self.planner.robot
        tracking = self.planner.tracking
        centre = np.clip(np.zeros(self.n), self.k_lo, self.k_hi) if shrink_toward is None else shrink_toward
        group = max(1, int(self.planner.torque_group))
        coarse = 4  # the affine bound runs on hulls of `coarse` boxes (it costs more per box)

        def shrunk(f):
            return centre + f * (self.k_lo - centre), centre + f * (self.k_hi - centre)

        def boxes_for(scales, merge):
            per = [[reach.merge_rows(x, merge) for x in self.reach.state_boxes(*shrunk(f))] for f in scales]
            return [
                Interval(np.concatenate([p[c].lo for p in per]), np.concatenate([p[c].hi for p in per]))
                for c in range(4)
            ], len(per[0][0].lo)

        def plain_bound(scales):
            """(sup, nominal, robust, excess, rows per level): the interval bound of every level at
            once; the robust term includes lambda's excess over |w_bar| on the tube (h < 0)."""
            boxes, nb = boxes_for(scales, group)
            wp = reach.interval_passivity_regressor(robot, *boxes)
            excess = reach.barrier_excess(robot, boxes[0], theta_lo, theta_hi, tracking, rows=self.planner.spread_rows)
            return (*reach.torque_bound(wp, theta0, theta_lo, theta_hi, excess), excess, nb)

        def take_largest_fit(scales, sup, nb):
            """Adopt the largest shrink level whose bound fits the limits (False if none does)."""
            ratio = (sup / limit).reshape(len(scales), nb, -1).max((1, 2))
            for f, r in zip(scales, ratio):
                if r <= 1.0:
                    self.k_lo, self.k_hi = shrunk(f)
                    self.torque_ratio = float(r)
                    return True
            return False

        whole, *_ = plain_bound([1.0])
        if (whole / limit).max() <= 1.0:
            self.torque_ratio = float((whole / limit).max())
            return True
        point = np.array_equal(self.k_lo, centre) and np.array_equal(self.k_hi, centre)
        steps = 0 if point else self.planner.torque_shrink_steps  # nothing to shrink
        scales = [0.5**s for s in range(1, steps + 1)]
        segment = bool(steps) and np.array_equal(self.k_lo, self.k_hi)  # a point: the segment to the centre
        if segment:  # in eighths (one plan's motion, as large as certifiable), then the finest halving
            scales = [j / 8 for j in range(7, 0, -1)] + scales[3:]
            if self.planner.config.continuation:  # and the centre itself (k = 0 in refinement)
                scales.append(0.0)
        nb = len(whole)
        if scales and (whole / limit).max() <= PLAIN_SHRINK_RATIO:
            sup, *_, nb = plain_bound(scales)
            if take_largest_fit(scales, sup, nb):  # the plain bound admits a shrunk box
                return True
        else:  # far over: shrinking does not rescue the plain bound (its tube terms stay); save the time
            sup = np.full((len(scales) * nb, self.n), np.inf)
        # The affine bound, one level at a time (it costs more per box); adopt the largest level that fits.
        scales = [1.0] + scales
        sup = np.concatenate([whole, sup]).reshape(len(scales), nb, -1)

        def affine_ratio(level):
            bound = self._affine_bound([scales[level]], shrunk, group * coarse, nb, coarse, theta0, theta_lo, theta_hi)
            bound = np.minimum(sup[level], bound)
            return bound, float((bound / limit).max())

        def walk_up():
            """From the second smallest level, up while it fits (a larger box contains a smaller
            one: stop at the first misfit; points on a segment: nearly monotone), down to the
            smallest if it does not."""
            start = max(0, len(scales) - 2)
            for level in (start, *range(start + 1, len(scales))):
                last, ratio = affine_ratio(level)
                if ratio <= 1.0:
                    break
            else:
                return None, last
            fitted = (level, ratio)
            for level in reversed(range(fitted[0])):
                _, ratio = affine_ratio(level)
                if ratio > 1.0:
                    break
                fitted = (level, ratio)
            return fitted, last

        fitted, last = walk_up()
        if fitted is not None:
            self.k_lo, self.k_hi = shrunk(scales[fitted[0]])
            self.torque_ratio = fitted[1]
            return True
        i, j = np.unravel_index(np.argmax(last / limit), last.shape)
        t_box = self.reach.edges[min(i * group, len(self.reach.t_mid) - 1)]
        self.torque_infeasible = True
        self._fail(
            f"torque limit of joint {j + 1} cannot be guaranteed (bound {last[i, j]:.1f} N m > "
            f"{limit[j]:.1f} N m from t = {t_box:.2f} s, robust term included)"
        )
        return False

    def _affine_bound(self, scales, shrunk, merge, nb, coarse, theta0, theta_lo, theta_hi):
        """sup |u| (levels * nb, n) of the affine enclosure on hulls of `merge` intervals, given for each
        of the nb finer boxes per level (each lies inside its hull)."""
        pl = self.planner
        per = [self.reach.tube_states(*shrunk(f), group=merge) for f in scales]
        states = [concat_rows([p[c] for p in per]) for c in range(4)]
        wp = reach.affine_passivity_regressor(pl.robot, *states)
        q_box = Interval(states[0].lo, states[0].hi)
        rows = max(1, pl.spread_rows // coarse)
        excess = reach.barrier_excess(pl.robot, q_box, theta_lo, theta_hi, pl.tracking, rows=rows)
        sup, _, _ = reach.affine_torque_bound(wp, theta0, theta_lo, theta_hi, excess)
        nbig = len(per[0][0].c)
        fine = np.arange(len(scales) * nb)
        return sup[(fine // nb) * nbig + (fine % nb) // coarse]  # the hull containing each fine box

    # -- collision pairs -------------------------------------------------------------------------
    def _collision_pairs(self):
        pl = self.planner
        spheres, lips = pl.spheres, pl.lipschitz
        r = self.reach
        k_mid = 0.5 * (self.k_lo + self.k_hi)
        k_half = 0.5 * (self.k_hi - self.k_lo)
        c, jac = reach.sphere_centres(pl.robot.tree, spheres, r.q_mid(k_mid))
        k_dev = np.abs(r.w_mid)[:, None] * (r.kr * k_half)[None, :]  # |q_mid(k) - q_mid(k_mid)|
        self.spread = reach.local_spread(pl.robot.tree, lips, np.linalg.norm(jac, axis=-1), r.rho, r.rho + k_dev)
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
        c, dc = reach.sphere_centres(pl.robot.tree, pl.spheres, qm, with_jacobian)
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
            pl.robot.tree, pl.robot.end_effector, qc.reshape(-1, n), vc.reshape(-1, n), ac.reshape(-1, n)
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
# The planner
# ---------------------------------------------------------------------------------------------


class SafePlanner:
    """ARMOUR-style planner for one robot, scene and payload.

    config: scenario `Planner` record (duration_s, num_time_intervals, num_cost_samples, cost,
    goal_q_rad, solver, max_solve_time_s, max_iterations, budget, k_center_rad, k_range_rad, floor_z_m).
    obstacles: scenario Obstacle records or a reachability.Boxes. payload: Dumbbell or None.
    tracking: controller.TrackingBounds (the controller's ultimate bound with ITS gains Kr; None
    means perfect tracking, for tests only). torque_noise: scenario.noise's declared bound (ratio,
    floor N m), which planner.exciting_weighting divides the cost's rows by (None: its default).
    """

    def __init__(
        self,
        robot: RobotModel,
        config: Planner,
        obstacles: Iterable[Obstacle] | reach.Boxes = (),
        payload: Dumbbell | None = None,
        tracking: TrackingBounds | None = None,
        floor: bool = True,
        torque_shrink_steps: int = 4,
        torque_group: int = 2,
        spread_rows: int = 4,
        torque_noise: tuple[float, float] | None = None,
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
        self.floor_exempt = _floor_exempt(robot.tree, self.spheres)
        self.tracking = TrackingBounds.coerce(tracking, n)
        self.torque_shrink_steps = torque_shrink_steps
        self.torque_group = torque_group
        self.spread_rows = spread_rows  # torque boxes per hull on which the M spread mu is bounded
        if torque_noise is None:  # the scenario's default
            from safesysid.systems.config import Noise

            torque_noise = (Noise.declared_torque_ratio, Noise.declared_torque_floor_Nm)
        self.torque_noise = torque_noise  # the estimator's declared bound (ratio, floor N m) per sample

    @property
    def weighs_rows(self) -> bool:
        """planner.exciting_weighting noise: the exciting cost divides W_e's rows by row_weights."""
        return getattr(self.config, "exciting_weighting", "none") == "noise"

    def row_weights(self, q: np.ndarray, v: np.ndarray, a: np.ndarray, theta0: ArrayLike) -> np.ndarray:
        """1 / the declared torque-noise bound of each W_e row (samples x joints, flattened) of the
        nominal model theta0 along (q, v, a)."""
        ratio, floor = self.torque_noise
        tau = self.robot.inverse_dynamics(q, v, a, np.asarray(theta0, float))
        return (1.0 / (ratio * np.abs(tau) + floor)).ravel()

    def problem(
        self,
        q0: ArrayLike,
        v0: ArrayLike,
        a0: ArrayLike,
        theta0: ArrayLike,
        theta_lo: ArrayLike,
        theta_hi: ArrayLike,
        mode: str | None = None,
        past: np.ndarray | None = None,
        k_box: tuple[np.ndarray, np.ndarray] | None = None,
        certify_torque: bool = True,
        shrink_toward: np.ndarray | None = None,
        box_scale: float = 1.0,
    ) -> PlanningProblem:
        """k_box: a sub-box (e.g. one point); certify_torque False: no torque check (the wider solve
        of point_refinement); shrink_toward: where the torque check shrinks the box (PlanningProblem);
        box_scale < 1: the limit box shrunk by it toward k = 0."""
        return PlanningProblem(
            self, q0, v0, a0, theta0, theta_lo, theta_hi, mode, past, k_box, certify_torque, shrink_toward, box_scale
        )

    def executed_rows(self, plan: PlanResult, duration_s: float, theta0: ArrayLike | None = None) -> np.ndarray:
        """W_e rows (rows, 10) of the first duration_s of an accepted plan, at the exciting cost's
        sample spacing, weighted as the cost weights its rows (row_weights under theta0, the
        robot's nominal when None): the `past` of the next planning call when
        planner.cumulative_excitation."""
        cfg = self.config
        t = np.arange(0.0, duration_s, cfg.duration_s / (cfg.num_cost_samples - 1))
        q, v, a = plan.evaluate(t)
        rows = ee_standard_regressor(self.robot.tree, self.robot.end_effector, q, v, a).reshape(-1, 10)
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
            prob = self.problem(q0, v0, a0, theta0, theta_lo, theta_hi, mode, past)
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
        mode = args[6]
        wide = self.problem(*args, certify_torque=False, box_scale=self.config.refinement_scale)
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
            point = self.problem(*args, k_box=(target, target), shrink_toward=base)
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
        nxt = self.problem(q, v, a, *args[3:6], args[6], None, k_box=(zero, zero))
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
        from pydrake.autodiffutils import ExtractGradient, ExtractValue, InitializeAutoDiff
        from pydrake.solvers import IpoptSolver, MathematicalProgram, SnoptSolver, SolverOptions

        cfg = self.config
        n = self.n
        record = {}  # x bytes -> [cost, min slack]

        def key(x):
            return np.asarray(x, float).tobytes()

        deadline = self._deadline(t_start)

        def check_time():
            if deadline < np.inf and time.perf_counter() > deadline:
                raise _WallTimeExceeded(_CAP_MESSAGE)

        def cost_eval(x):
            kk = key(x)
            if kk not in prob._cache:
                prob._cache[kk] = prob.cost(x)
            val, grad = prob._cache[kk]
            record.setdefault(kk, [None, None])[0] = val
            return val, grad

        con_cache = {}

        def con_eval(x):
            kk = key(x)
            if kk not in con_cache:
                con_cache[kk] = prob.collision_grouped(x)
            vals, jac = con_cache[kk]
            record.setdefault(kk, [None, None])[1] = vals.min() if len(vals) else np.inf
            return vals, jac

        def cost_fn(x):
            check_time()
            if x.dtype == object:
                val, grad = cost_eval(ExtractValue(x)[:, 0])
                from pydrake.autodiffutils import AutoDiffXd

                return AutoDiffXd(val, grad @ ExtractGradient(x))
            return cost_eval(x)[0]

        def con_fn(x):
            check_time()
            if x.dtype == object:
                vals, jac = con_eval(ExtractValue(x)[:, 0])
                return InitializeAutoDiff(vals, jac @ ExtractGradient(x))[:, 0]
            return con_eval(x)[0]

        prog = MathematicalProgram()
        k = prog.NewContinuousVariables(n, "k")
        prog.AddBoundingBoxConstraint(prob.k_lo, prob.k_hi, k)
        prog.AddCost(cost_fn, k)
        if prob.num_constraints:
            m = prob.num_constraints
            prog.AddConstraint(con_fn, np.full(m, COLLISION_SOLVER_MARGIN_M), np.full(m, np.inf), k)
        k0, fallback = self._initial_guess(prob, k_init)
        prog.SetInitialGuess(k, k0)
        remaining = max(0.05, deadline - time.perf_counter())  # inf: no time limit for the solver
        options = SolverOptions()
        if cfg.solver == "snopt":
            solver = SnoptSolver()
            sid = solver.solver_id()
            options.SetOption(sid, "Major iterations limit", int(cfg.max_iterations))
            if remaining < np.inf:
                options.SetOption(sid, "Time limit", float(remaining))
            options.SetOption(sid, "Major optimality tolerance", 1e-4)
            options.SetOption(sid, "Major feasibility tolerance", 1e-6)
        else:
            solver = IpoptSolver()
            sid = solver.solver_id()
            options.SetOption(sid, "max_iter", int(cfg.max_iterations))
            if remaining < np.inf:
                options.SetOption(sid, "max_wall_time", float(remaining))
            options.SetOption(sid, "hessian_approximation", "limited-memory")
            if prob.mode == "exciting":
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
        cands = []
        try:
            result = solver.Solve(prog, k0, options)
            status = str(result.get_solution_result()).split(".")[-1]
            x_sol = np.clip(result.GetSolution(k), prob.k_lo, prob.k_hi)
            cands.append((cost_eval(x_sol)[0], x_sol, "solved" if result.is_success() else "best_feasible"))
        except _WallTimeExceeded:
            status = "wall_time_cap"
        except Exception as err:  # noqa: BLE001 -- solver failure: fall back on what was evaluated
            status = "wall_time_cap" if _CAP_MESSAGE in str(err) else f"solver error: {str(err).splitlines()[0]}"
        if status.startswith("solver error") and not record:
            return None, "solver_failed", status
        # Candidates: the solver's answer and every evaluated point; keep the best verified feasible.
        for kk, (c, slack) in record.items():
            if c is not None and slack is not None and slack >= 0:
                cands.append((c, np.frombuffer(kk), "best_feasible"))
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


def _floor_exempt(tree, spheres):
    """Spheres whose height no joint can change (world-fixed, or carried only by root joints with a
    vertical axis): the floor constraint is constant for them and the base sits on the floor."""
    out = np.zeros(len(spheres), bool)
    anc = tree.ancestors()
    for s in range(len(spheres)):
        b = spheres.body[s]
        if b < 0:
            out[s] = True
            continue
        joints = np.flatnonzero(anc[:, b])
        vertical = []
        for j in joints:
            if tree.parent[j] >= 0 or tree.prismatic[j]:
                vertical.append(False)
                continue
            axis_world = tree.X_parent_joint[j, :3, :3] @ tree.axis[j]
            vertical.append(abs(abs(axis_world[2]) - 1) < 1e-12)
        out[s] = all(vertical)
    return out
