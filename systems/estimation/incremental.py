"""Algorithm 1 chunk by chunk: the IncrementalEstimator that keeps per-segment rows, latches
consistency and intersects each update with the published box (the Estimate it publishes: estimate.py).
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.model import inertial
from safesysid.systems.model.uncertainty import parameter_radius

from .acceleration_bound import certify_segments
from .delay import DelayInverse
from .enclosure import box_is_consistent, interval_hull, set_membership_bounds, torque_row_radius
from .estimate import Estimate, quadrature_assumption
from .lag import LagInverse
from .log_cholesky import cost_grad_hess, nearest_consistent, solve_log_cholesky
from .physical import prune_box
from .segments import Reference, SegmentRows, build_segment_rows, segment_bounds
from .settings import EstimatorError, EstimatorSettings

if TYPE_CHECKING:
    from safesysid.systems.model.robot_model import RobotModel


def _names(mask):
    return [inertial.NAMES[k] for k in np.flatnonzero(mask)]


def _case(centre, radius, theta):
    """Which case of Theorem 2 the box is in (Estimate.case), from the least-squares solution theta."""
    box_ok, lam = box_is_consistent(centre, radius)
    at_centre = np.abs(theta - centre) <= 1e-6 * (np.abs(centre) + radius + 1e-9)
    if box_ok:
        return "interior"  # exact hull of θ*([m]); θ* linear in m on the whole box
    if lam > 0 and np.all(at_centre):
        return "interior_at_m"  # LMI inactive at m but reachable inside [m]; box encloses truth
    return "lmi_active"  # θ0 near the LMI boundary; box around Y⁺U(m) still encloses truth


class IncrementalEstimator:
    """Accepts joint-log chunks; keeps per-segment rows so old segments are never recomputed.

    prior: optional (lower, upper) of θ_e to intersect with (e.g. the paper's Table II box). It
    also bounds θ_e in the quadrature term; without one that term takes |θ_e − θ_e0| ≤ |θ_e0|
    (θ_e0 = prior_nominal, or the model's end effector).

    Consistency is latched: the first update whose data contradict a declared bound (two
    enclosures that do not meet, an infeasible set-membership LP, a box disjoint from the
    published one, a torque faster than declared) sets `consistent` False for good, and from then
    on the last consistent box (or the prior) is published unchanged: a published box is never
    outside the previous one, nor outside the prior.
    """

    def __init__(self, robot, *, settings: EstimatorSettings | None = None, prior=None, prior_nominal=None):
        self.robot = robot
        self.settings = st = settings or EstimatorSettings()
        if st.integration not in ("trapezoid", "euler"):
            raise EstimatorError(f"estimator.integration: {st.integration!r} is not trapezoid or euler")
        if st.torque_signal not in ("held", "continuous"):
            raise EstimatorError(f"estimator.torque_signal: {st.torque_signal!r} is not held or continuous")
        if st.quadrature_safety < 2:
            raise EstimatorError(f"estimator.quadrature_safety: {st.quadrature_safety} must be >= 2")
        lag = st.lag_interval()
        if lag[1] > 0 and st.torque_signal != "held":
            raise EstimatorError(f"estimator.torque_lag_s: {st.torque_lag_s} needs a held torque signal")
        self._unlag = LagInverse(lag, st.segment_gap_s()) if lag[1] > 0 else None
        if st.derive_acceleration_bound and (st.torque_signal != "held" or st.acceleration_bound_rad_s2 is not None):
            raise EstimatorError("estimator.derive_acceleration_bound needs a held torque and no declared bound")
        if st.torque_delay_s and not (st.torque_signal == "held" and st.hold_period_s):
            raise EstimatorError(f"estimator.torque_delay_s: {st.torque_delay_s} needs a held torque and its period")
        self._unshift = DelayInverse(st.torque_delay_s, st.hold_period_s) if st.torque_delay_s else None
        self.n = robot.n
        rest = robot.rest_mask()
        self.theta_r = robot.theta[rest].copy()
        self.theta_r_radius = parameter_radius(robot, st.theta_r_ratio, st.theta_r_ratio, floors=st.theta_r_floor)[rest]
        self.rows = SegmentRows.empty(self.n, len(self.theta_r))
        self._pending = None  # (t, q, v, tau, reading radius) of the unfinished tail
        self._consumed = 0  # global index of the first pending sample
        self.num_samples = 0
        self.prior = None if prior is None else (np.asarray(prior[0], float), np.asarray(prior[1], float))
        nominal = robot.theta_e if prior_nominal is None else np.asarray(prior_nominal, float)
        self.prior_nominal = nominal.copy()  # published before the first update (need not be consistent)
        # The gripper's own parameters (the end-effector link without payload) in the robot box:
        # what the payload's bounding volume is subtracted from (estimation/physical.py).
        rad_g = parameter_radius(robot, st.theta_r_ratio, st.theta_r_ratio, floors=st.theta_r_floor)[robot.ee_slice]
        self.gripper_box = (robot.theta_e - rad_g, robot.theta_e + rad_g)
        self._cuts = []  # cutting planes of the pruning LPs (valid for every box: kept across updates)
        self.eta = (
            inertial.theta_to_log_cholesky(nominal) if inertial.is_physically_consistent(nominal) else np.zeros(10)
        )
        self.estimate: Estimate | None = None
        self.consistent = True  # latched: False from the first inconsistent update on
        self.update_times_s = []
        self.messages = []

    # -- data -------------------------------------------------------------------------------
    def add(
        self,
        t: ArrayLike,
        q: ArrayLike,
        v: ArrayLike,
        tau: ArrayLike,
        *,
        reference: Reference | None = None,
        acceleration_bound: ArrayLike | None = None,
    ) -> int:
        """Append samples (any chunk size); builds the segments that became complete. reference:
        the motion between the samples, times -> (q, v, a), when known (A5 is then checked).
        acceleration_bound: |q̈_j| ≤ it between these samples (rad/s², scalar or (n,); default
        settings.acceleration_bound_rad_s2): the quadrature is then certified (`certified_rows`)."""
        if acceleration_bound is None:
            acceleration_bound = self.settings.acceleration_bound_rad_s2
        t = np.atleast_1d(np.asarray(t, float))
        q, v, tau = (np.atleast_2d(np.asarray(x, float)) for x in (q, v, tau))
        if q.shape != (len(t), self.n) or v.shape != q.shape or tau.shape != q.shape:
            raise EstimatorError(f"expected {self.n} joints per sample, got q {q.shape}, v {v.shape}, tau {tau.shape}")
        if not (
            np.all(np.isfinite(t)) and np.all(np.isfinite(q)) and np.all(np.isfinite(v)) and np.all(np.isfinite(tau))
        ):
            raise EstimatorError("NaN or inf in the estimator input")
        if self._unshift is not None:  # each step paired with its reading, once it has arrived
            t, q, v, tau = self._unshift.push(t, q, v, y=tau)
        rho = None  # how far each τ is from the sensor's reading (a lag interval)
        if self._unlag is not None:  # the readings of a lagged sensor, one sample late
            t, q, v, tau, rho = self._unlag.push(t, q, v, y=tau)
        rho = np.zeros_like(tau) if rho is None else rho
        if self._pending is not None:
            if len(t) and len(self._pending[0]) and t[0] <= self._pending[0][-1]:
                raise EstimatorError(f"time is not strictly increasing at t={t[0]:.6g}")
            t, q, v, tau, rho = (np.concatenate([a, b]) for a, b in zip(self._pending, (t, q, v, tau, rho)))
        if np.any(np.diff(t) <= 0):
            raise EstimatorError("time is not strictly increasing")
        self.num_samples += len(t) - (0 if self._pending is None else len(self._pending[0]))
        bounds, next_start = segment_bounds(t, self.settings.horizon_s, self.settings.segment_gap_s())
        if len(bounds):
            new = build_segment_rows(
                self.robot,
                t,
                q,
                v,
                tau,
                bounds,
                self.settings,
                theta_box=self.theta_box(),
                index_offset=self._consumed,
                reading_radius=rho if rho.any() else None,
                reference=reference,
            )
            new = certify_segments(  # A5 certified from a declared or derived bound (or the step flagged)
                new,
                self.robot,
                self.settings,
                (t, q, v, tau, rho),
                bounds,
                theta_box=self.theta_box(),
                declared=acceleration_bound,
                reference=reference,
            )
            if len(self.rows) and len(new) and new.start_index[0] == self.rows.end_index[-1]:
                new.shared_prev[0] = True
            self.rows = self.rows.concat(new)
        self._consumed += next_start
        self._pending = tuple(x[next_start:] for x in (t, q, v, tau, rho))
        return len(bounds)

    def predicted_radius(self, t: ArrayLike, q: ArrayLike, v: ArrayLike, *, tau: ArrayLike) -> np.ndarray | None:
        """Half-widths of the Theorem-2 box (torque + θ_r + quadrature terms, the `map` left
        inverse) if the candidate log (t, q, v, τ: e.g. a plan's samples with its predicted
        torque) were added to the data so far; the estimator is not changed. A planner can rank
        candidate plans by it (it does not depend on the noise, only on the motion and the torque
        level). None when the data would not identify θ_e."""
        t, q, v, tau = (np.asarray(x, float) for x in (t, q, v, tau))
        bounds, _ = segment_bounds(t, self.settings.horizon_s, self.settings.segment_gap_s())
        new = build_segment_rows(self.robot, t, q, v, tau, bounds, self.settings, theta_box=self.theta_box())
        hull, cond = interval_hull(self.rows.concat(new), self.theta_r, self.theta_r_radius, settings=self.settings)
        if hull is None or cond > self.settings.max_condition:
            return None
        return hull["rad_torque"] + hull["rad_theta_r"] + hull["rad_quad"]

    def theta_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(centre, radius) of the box the whole-robot θ lies in: [θ_r] and the published [θ_e]
        (or the prior), for the quadrature bound."""
        centre, radius = self.robot.theta.copy(), np.zeros(14 * self.n)
        radius[self.robot.rest_mask()] = self.theta_r_radius
        ee = self.robot.ee_slice
        box = (self.estimate.lower, self.estimate.upper) if self.estimate is not None else self.prior
        if box is not None and np.all(np.isfinite(box[0])) and np.all(np.isfinite(box[1])):
            centre[ee], radius[ee] = 0.5 * (box[0] + box[1]), 0.5 * (box[1] - box[0])
        else:
            centre[ee], radius[ee] = self.prior_nominal, np.abs(self.prior_nominal)
        return centre, radius

    # -- estimate ---------------------------------------------------------------------------
    def update(self) -> Estimate:
        """Algorithm 1 on all segments so far; returns the Estimate (also kept in .estimate)."""
        start = time.perf_counter()
        st = self.settings
        S = len(self.rows)
        self._require_data(S)
        hull, cond = interval_hull(self.rows, self.theta_r, self.theta_r_radius, settings=st)
        prev = self.estimate
        if hull is None or cond > st.max_condition:
            return self._finish(self._prior_estimate(cond, S, f"not identifiable yet (cond(Y) = {cond:.3g})"), start)
        centre = hull["centre"]
        sol = self._least_squares(hull)
        radius = hull["rad_torque"] + hull["rad_theta_r"] + hull["rad_quad"] + hull["rad_round"]
        # Evidence that a declared assumption failed (each one empties the set the truth is in).
        problems = []
        lo, hi = self._update_box(centre, radius, problems)
        case = _case(centre, radius, sol.theta)
        data_lo, data_hi, new_lo, new_hi = self._published_box(lo, hi, prev, problems)
        notes, a5, quad_ratio = self._notes()
        if problems:
            if self.consistent:
                notes.insert(
                    0,
                    "inconsistent data (" + "; ".join(problems) + "): torque noise or θ_r outside the "
                    "declared bounds, or the model is wrong; keeping the last consistent interval",
                )
            self.consistent = False
        self.messages.extend(notes)
        if not self.consistent:  # latched: publish the last consistent box (or the prior) unchanged
            keep = prev or self._prior_estimate(np.inf, 0, "")
            theta_e, new_lo, new_hi = keep.theta_e.copy(), keep.lower.copy(), keep.upper.copy()
            data_lo, data_hi = keep.data_lower.copy(), keep.data_upper.copy()
            lo, hi = data_lo, data_hi  # this update's own box is evidence of a failure, not an interval
        else:
            self.eta = sol.eta  # the consistent least-squares solution stays the warm start
            # Publish the nominal clipped into the interval: the truth is inside it, so per parameter
            # the projection is never farther from the truth (it matters for barely excited inertias).
            theta_e = np.clip(sol.theta, new_lo, new_hi)
        est = self._estimate(theta_e, (new_lo, new_hi), sol=sol, hull=hull, cond=cond, case=case)
        est.update_lower, est.update_upper, est.data_lower, est.data_upper = lo, hi, data_lo, data_hi
        est.message, est.problems = "; ".join(notes), problems
        est.quadrature_ratio, est.quadrature_assumption = quad_ratio, a5
        return self._finish(est, start)

    def _require_data(self, S):
        """EstimatorError unless the S segments give at least 10 rows."""
        st = self.settings
        if S * self.n >= 10:
            return
        hint = (
            ""
            if st.segment_gap_s() == st.max_gap_s
            else (
                f" (held torque: a step longer than {st.segment_gap_s():.3g} s, 1.5 hold periods, ends a segment; "
                "for a log sampled slower than its controller set estimator.hold_period_s or "
                "estimator.torque_signal: continuous)"
            )
        )
        raise EstimatorError(
            f"too little data: {S} segment(s) of {st.horizon_s} s; need at least "
            f"{int(np.ceil(10 / self.n))} gap-free segments{hint}"
        )

    def _least_squares(self, hull):
        """The physically consistent least-squares solution (log-Cholesky NLP). Warm start: previous η,
        or P⁻¹ of the unconstrained solution when it is consistent (then it is the optimum and the
        NLP only confirms it) — whichever costs less."""
        A, b, c = hull["A"], hull["b"], hull["c"]
        starts = [self.eta, inertial.theta_to_log_cholesky(nearest_consistent(hull["centre"]))]
        eta0 = min(starts, key=lambda e: cost_grad_hess(e, A, b, c)[0])
        sol = solve_log_cholesky(A, b, c, eta0, solver=self.settings.solver, newton_steps=self.settings.newton_steps)
        if not np.all(np.isfinite(sol.theta)):
            sol.eta, sol.theta = self.eta, inertial.log_cholesky_to_theta(self.eta)
            self.messages.append("solver failed; kept the previous estimate")
        return sol

    def _update_box(self, centre, radius, problems):
        """This update's box: Theorem 2's hull, the `map` estimate's second enclosure, the prior
        and the set-membership LP intersected; a contradiction is appended to `problems`."""
        st = self.settings
        lo = np.nextafter(centre - radius, -np.inf)
        hi = np.nextafter(centre + radius, np.inf)
        if np.any(self.rows.violated):
            problems.append(
                f"the measured torque changes faster than the declared {st.torque_rate_limit_Nm_s} N·m/s "
                f"in {int(self.rows.violated.sum())} segment(s)"
            )
        if np.any(self.rows.accel_violated):
            bound = (
                "the dynamics allow under the held torque (derived acceleration bound)"
                if st.derive_acceleration_bound
                else f"the declared acceleration bound {st.acceleration_bound_rad_s2} rad/s²"
            )
            problems.append(
                f"the joint motion is faster than {bound} in {int(self.rows.accel_violated.sum())} segment(s)"
            )
        # The same hull with the other left inverse (rows scaled by their declared bound): also
        # an enclosure, often tighter on the mass; keep the intersection.
        if st.point_estimate == "map":
            alt, _ = interval_hull(
                self.rows,
                self.theta_r,
                self.theta_r_radius,
                settings=replace(st, point_estimate="paper", row_weighting="bound"),
            )
            if alt is not None:
                r_alt = alt["rad_torque"] + alt["rad_theta_r"] + alt["rad_quad"] + alt["rad_round"]
                lo_alt = np.maximum(lo, np.nextafter(alt["centre"] - r_alt, -np.inf))
                hi_alt = np.minimum(hi, np.nextafter(alt["centre"] + r_alt, np.inf))
                if np.any(lo_alt > hi_alt):
                    problems.append(
                        "the two least-squares enclosures do not meet in "
                        f"{[inertial.NAMES[k] for k in np.flatnonzero(lo_alt > hi_alt)]}"
                    )
                else:
                    lo, hi = lo_alt, hi_alt
        # A2: the truth is in the prior, so the update box is intersected with it (before the LP,
        # whose polytope it bounds: a tighter LP).
        if self.prior is not None and not problems:
            lo, hi = np.maximum(lo, self.prior[0]), np.minimum(hi, self.prior[1])
            if np.any(lo > hi):
                problems.append(f"the data box does not meet the prior in {_names(lo > hi)}")
        params = {"none": [], "mass": [0], "all": list(range(10))}[st.set_membership]
        if params and not problems:
            prev = self.estimate if self.consistent else None  # its data box: what older segments said (A2)
            box = dict(box_lo=lo, box_hi=hi, previous=None if prev is None else (prev.data_lower, prev.data_upper))
            sm_lo, sm_hi, feasible = set_membership_bounds(
                self.rows, self.theta_r, self.theta_r_radius, settings=st, params=params, **box
            )
            if not feasible:
                problems.append("the set-membership LP is infeasible")
            else:
                lo = np.where(np.isnan(sm_lo), lo, np.maximum(lo, sm_lo))
                hi = np.where(np.isnan(sm_hi), hi, np.minimum(hi, sm_hi))
        return lo, hi

    def _published_box(self, lo, hi, prev, problems):
        """(data box, published box): the update box intersected with the previous data-driven
        interval (or the prior), then pruned with physical knowledge inside the published one."""
        old = (prev.data_lower, prev.data_upper) if prev is not None else self.prior
        data_lo, data_hi = (lo, hi) if old is None else (np.maximum(lo, old[0]), np.minimum(hi, old[1]))
        if np.any(data_lo > data_hi):
            problems.append(f"the new interval does not meet the published one in {_names(data_lo > data_hi)}")
        new_lo, new_hi = data_lo, data_hi
        if self.settings.physical_pruning and not problems:
            p_lo, p_hi, feasible = prune_box(
                data_lo, data_hi, volume=self.settings.payload_volume, gripper=self.gripper_box, cuts=self._cuts
            )
            if not feasible:
                problems.append("the data box contradicts the payload's physical knowledge (LMI, bounding volume)")
            else:
                new_lo, new_hi = (
                    (p_lo, p_hi) if prev is None else (np.maximum(p_lo, prev.lower), np.minimum(p_hi, prev.upper))
                )
                if np.any(new_lo > new_hi):
                    problems.append(f"the pruned interval does not meet the published one in {_names(new_lo > new_hi)}")
        return data_lo, data_hi, new_lo, new_hi

    def _notes(self):
        """(notes on the quadrature term, A5's status, the largest quadrature / torque radius ratio)."""
        notes = []
        a5 = quadrature_assumption(self.rows)
        if a5 == "violated":
            notes.append(
                f"A5 (quadrature) false on {int(self.rows.a5_violated.sum())} segment(s): the motion between the "
                "samples is faster than they show; those rows are bounded on sub-steps"
            )
        elif a5 == "certified":
            notes.append(
                f"A5 (quadrature) not shown on {int((~self.rows.a5_shown & ~self.rows.a5_checked).sum())} segment(s): "
                "their quadrature term is the certificate from the acceleration bound"
            )
        quad_ratio = float(np.max(self.rows.quad / np.maximum(torque_row_radius(self.rows), 1e-300)))
        if quad_ratio > self.settings.quadrature_warn_ratio:
            notes.append(
                f"quadrature term up to {quad_ratio:.2f} of a row's torque radius: the motion is not "
                "resolved by the sampling"
            )
        return notes, a5, quad_ratio

    def _estimate(self, theta_e, box, *, sol, hull, cond, case):
        """The Estimate of θ_e in `box` (the whole robot's θ and box around it; the update's own
        boxes and notes are filled in by the caller)."""
        robot = self.robot
        first = self._first_order()
        theta = robot.theta.copy()
        theta[robot.ee_slice] = theta_e
        t_lo, t_hi = self._robot_box()
        t_lo[robot.ee_slice], t_hi[robot.ee_slice] = box
        return Estimate(
            theta_e=theta_e,
            lower=box[0],
            upper=box[1],
            theta=theta,
            theta_lower=t_lo,
            theta_upper=t_hi,
            eta=sol.eta,
            theta_ls=hull["centre"],
            update_lower=None,
            update_upper=None,
            radius_torque=hull["rad_torque"],
            radius_theta_r=hull["rad_theta_r"],
            radius_quadrature=hull["rad_quad"],
            radius_rounding=hull["rad_round"],
            case=case,
            consistent=self.consistent,
            cond_Y=cond,
            num_segments=len(self.rows),
            num_samples=self.num_samples,
            solver={
                "name": sol.solver,
                "success": sol.success,
                "result": sol.message,
                "cost": sol.cost,
                "grad_norm": sol.grad_norm,
                "newton_steps": sol.newton_steps,
            },
            first_order_lower=None if first is None else first[0],
            first_order_upper=None if first is None else first[1],
        )

    def _first_order(self):
        """The paper's first-order interval on the same data (see Estimate.first_order_lower)."""
        paper = replace(self.settings, point_estimate="paper", row_weighting="none")
        hull, _ = interval_hull(self.rows, self.theta_r, self.theta_r_radius, settings=paper)
        if hull is None:
            return None
        radius = hull["rad_torque"] + hull["rad_theta_r"]
        return hull["centre"] - radius, hull["centre"] + radius

    def _finish(self, est, start):
        est.update_time_s = time.perf_counter() - start
        self.update_times_s.append(est.update_time_s)
        self.estimate = est
        return est

    def _robot_box(self):
        lo, hi = self.robot.theta.copy(), self.robot.theta.copy()
        mask = self.robot.rest_mask()
        lo[mask], hi[mask] = self.theta_r - self.theta_r_radius, self.theta_r + self.theta_r_radius
        return lo, hi

    def _prior_estimate(self, cond, S, message):
        prev = self.estimate
        if prev is not None and prev.case != "prior":
            prev.message = message
            return prev
        theta_e = self.prior_nominal.copy()
        lo, hi = self.prior if self.prior is not None else (np.full(10, -np.inf), np.full(10, np.inf))
        t_lo, t_hi = self._robot_box()
        t_lo[self.robot.ee_slice], t_hi[self.robot.ee_slice] = lo, hi
        theta = self.robot.theta.copy()
        theta[self.robot.ee_slice] = theta_e
        z = np.zeros(10)
        est = Estimate(
            theta_e,
            lo.copy(),
            hi.copy(),
            theta,
            t_lo,
            t_hi,
            self.eta,
            theta_e,
            lo.copy(),
            hi.copy(),
            z,
            z,
            z,
            z,
            "prior",
            self.consistent,
            cond,
            S,
            self.num_samples,
            {},
            message,
        )
        est.data_lower, est.data_upper = lo.copy(), hi.copy()
        return est

    def prior_estimate(self) -> Estimate:
        """What to publish before the first identification (nominal θ_e, prior box)."""
        return self._prior_estimate(np.inf, 0, "no data yet")


def identify(
    robot: RobotModel,
    t: ArrayLike,
    q: ArrayLike,
    v: ArrayLike,
    tau: ArrayLike,
    *,
    settings: EstimatorSettings | None = None,
    prior: tuple[ArrayLike, ArrayLike] | None = None,
    prior_nominal: ArrayLike | None = None,
) -> Estimate:
    """Algorithm 1 on a whole log (pure function): returns an Estimate."""
    est = IncrementalEstimator(robot, settings=settings, prior=prior, prior_nominal=prior_nominal)
    est.add(t, q, v, tau)
    return est.update()
