"""The torque certificate of a planning problem's k box (problem.PlanningProblem): the largest box
(the allowed one, or shrunk toward a centre by halves; on a point box, the points of the segment to
the centre) whose rigorous torque bound fits the limits. Plain interval bound on the whole box; if
that fails, on all shrink levels at once (one batched call); if all fail, again with the affine
(zonotope) enclosure of the regressor on hulls of `COARSE` boxes, whose tracking error keeps its
(e, r) coupling (interval_dynamics.affine_torque_bound: tighter, costlier)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from safesysid.systems.math.intervals import Interval
from safesysid.systems.planner.affine_forms import concat_rows
from safesysid.systems.planner.interval_dynamics import (
    affine_passivity_regressor,
    interval_passivity_regressor,
    merge_rows,
)
from safesysid.systems.planner.torque_certificate import affine_torque_bound, barrier_excess, torque_bound

if TYPE_CHECKING:
    from safesysid.systems.planner.reachability import PlanReach
    from safesysid.systems.planner.setup import PlannerSetup

# The plain interval bound is tried on the shrunk k boxes only when the whole box is at most this far
# over the limit (speed only: the affine bound is tried in any case, and every bound is rigorous).
PLAIN_SHRINK_RATIO = 1.6  # the solver aims this far inside; verification asks >= 0
COARSE = 4  # the affine bound runs on hulls of COARSE boxes (it costs more per box)


@dataclass
class TorqueFit:
    """The certified k box and its sup |u| / limit, or (k_lo None) why none fits."""

    k_lo: np.ndarray | None
    k_hi: np.ndarray | None
    ratio: float = np.nan
    why: str = ""


def fit_torque_box(
    planner: PlannerSetup,
    reach: PlanReach,
    k_box: tuple[np.ndarray, np.ndarray],
    *,
    theta: tuple[np.ndarray, np.ndarray, np.ndarray],
    centre: np.ndarray,
) -> TorqueFit:
    """The largest part of the k box (k_lo, k_hi) of a planning problem (its planner and
    reachability) toward `centre` whose torque bound under the parameter box theta = (theta0,
    theta_lo, theta_hi) fits the limits."""
    return _TorqueBoxSearch(planner, reach, k_box, theta, centre).run()


class _TorqueBoxSearch:
    def __init__(self, planner, reach, k_box, theta, centre):
        self.reach = reach
        self.robot, self.tracking = planner.robot, planner.tracking
        self.limit = planner.robot.joint_params.torque_limit
        self.group = max(1, int(planner.torque_group))
        self.spread_rows = planner.spread_rows
        self.shrink_steps = planner.torque_shrink_steps
        self.continuation = planner.config.continuation
        self.theta0, self.theta_lo, self.theta_hi = theta
        (self.k_lo, self.k_hi), self.centre = k_box, centre

    def shrunk(self, f):
        return self.centre + f * (self.k_lo - self.centre), self.centre + f * (self.k_hi - self.centre)

    def run(self):
        whole, *_ = self.plain_bound([1.0])
        if (whole / self.limit).max() <= 1.0:
            return TorqueFit(self.k_lo, self.k_hi, float((whole / self.limit).max()))
        scales = self.shrink_levels()
        nb = len(whole)
        if scales and (whole / self.limit).max() <= PLAIN_SHRINK_RATIO:
            sup, *_, nb = self.plain_bound(scales)
            fit = self.take_largest_fit(scales, sup, nb)
            if fit is not None:  # the plain bound admits a shrunk box
                return fit
        else:  # far over: shrinking does not rescue the plain bound (its tube terms stay); save the time
            sup = np.full((len(scales) * nb, len(self.limit)), np.inf)
        # The affine bound, one level at a time (it costs more per box); adopt the largest level that fits.
        scales = [1.0] + scales
        sup = np.concatenate([whole, sup]).reshape(len(scales), nb, -1)
        fitted, last = self.walk_up(scales, sup, nb)
        if fitted is not None:
            return TorqueFit(*self.shrunk(scales[fitted[0]]), fitted[1])
        return TorqueFit(None, None, why=self.failure(last))

    def shrink_levels(self):
        """The shrink factors tried after the whole box, largest first."""
        point = np.array_equal(self.k_lo, self.centre) and np.array_equal(self.k_hi, self.centre)
        steps = 0 if point else self.shrink_steps  # nothing to shrink
        scales = [0.5**s for s in range(1, steps + 1)]
        segment = bool(steps) and np.array_equal(self.k_lo, self.k_hi)  # a point: the segment to the centre
        if segment:  # in eighths (one plan's motion, as large as certifiable), then the finest halving
            scales = [j / 8 for j in range(7, 0, -1)] + scales[3:]
            if self.continuation:  # and the centre itself (k = 0 in refinement)
                scales.append(0.0)
        return scales

    def boxes_for(self, scales, merge):
        per = [[merge_rows(x, merge) for x in self.reach.state_boxes(*self.shrunk(f))] for f in scales]
        return [
            Interval(np.concatenate([p[c].lo for p in per]), np.concatenate([p[c].hi for p in per])) for c in range(4)
        ], len(per[0][0].lo)

    def plain_bound(self, scales):
        """(sup, nominal, robust, excess, rows per level): the interval bound of every level at
        once; the robust term includes lambda's excess over |w_bar| on the tube (h < 0)."""
        boxes, nb = self.boxes_for(scales, self.group)
        wp = interval_passivity_regressor(self.robot, *boxes)
        excess = barrier_excess(
            self.robot, boxes[0], self.theta_lo, self.theta_hi, self.tracking, rows=self.spread_rows
        )
        return (*torque_bound(wp, self.theta0, self.theta_lo, theta_hi=self.theta_hi, excess=excess), excess, nb)

    def take_largest_fit(self, scales, sup, nb):
        """The largest shrink level whose bound fits the limits (None if none does)."""
        ratio = (sup / self.limit).reshape(len(scales), nb, -1).max((1, 2))
        for f, r in zip(scales, ratio):
            if r <= 1.0:
                return TorqueFit(*self.shrunk(f), float(r))
        return None

    def affine_ratio(self, level, scales, sup, nb):
        bound = self.affine_bound([scales[level]], nb)
        bound = np.minimum(sup[level], bound)
        return bound, float((bound / self.limit).max())

    def walk_up(self, scales, sup, nb):
        """((level, ratio) fitted or None, the last bound): from the second smallest level, up while
        it fits (a larger box contains a smaller one: stop at the first misfit; points on a segment:
        nearly monotone), down to the smallest if it does not."""
        start = max(0, len(scales) - 2)
        for level in (start, *range(start + 1, len(scales))):
            last, ratio = self.affine_ratio(level, scales, sup, nb)
            if ratio <= 1.0:
                break
        else:
            return None, last
        fitted = (level, ratio)
        for level in reversed(range(fitted[0])):
            _, ratio = self.affine_ratio(level, scales, sup, nb)
            if ratio > 1.0:
                break
            fitted = (level, ratio)
        return fitted, last

    def affine_bound(self, scales, nb):
        """sup |u| (levels * nb, n) of the affine enclosure on hulls of group * COARSE intervals, given
        for each of the nb finer boxes per level (each lies inside its hull)."""
        per = [self.reach.tube_states(*self.shrunk(f), group=self.group * COARSE) for f in scales]
        states = [concat_rows([p[c] for p in per]) for c in range(4)]
        wp = affine_passivity_regressor(self.robot, *states)
        q_box = Interval(states[0].lo, states[0].hi)
        rows = max(1, self.spread_rows // COARSE)
        excess = barrier_excess(self.robot, q_box, self.theta_lo, self.theta_hi, self.tracking, rows=rows)
        sup, _, _ = affine_torque_bound(wp, self.theta0, self.theta_lo, theta_hi=self.theta_hi, excess=excess)
        nbig = len(per[0][0].c)
        fine = np.arange(len(scales) * nb)
        return sup[(fine // nb) * nbig + (fine % nb) // COARSE]  # the hull containing each fine box

    def failure(self, last):
        i, j = np.unravel_index(np.argmax(last / self.limit), last.shape)
        t_box = self.reach.edges[min(i * self.group, len(self.reach.t_mid) - 1)]
        return (
            f"torque limit of joint {j + 1} cannot be guaranteed (bound {last[i, j]:.1f} N m > "
            f"{self.limit[j]:.1f} N m from t = {t_box:.2f} s, robust term included)"
        )
