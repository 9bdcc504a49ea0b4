"""Bounded least-squares fits of effect sets on the fit designs (their normal equations,
summed), scored on check designs.

Fits are bounded linear least squares (scipy lsq_linear on the Cholesky factor of the normal
equations, so each fit costs microseconds); the payload uses a log-Cholesky Gauss-Newton
(scipy least_squares) when the linear fit is not physically consistent.
"""

from __future__ import annotations

import numpy as np
from safesysid.systems.model import inertial
from safesysid.systems.model.robot_model import RobotModel

from .design import Design
from .effects import MAX_DELAY_S, TIME_LAWS, Params, effect_groups, group_bounds
from .time_laws import model_side_rows

DELAY_FINE_S = 0.005
TimeLaw = tuple[str, float]  # ("shift" | "lag", d [s]) applied to the model side
FoldParams = tuple[Params, ...]  # one fit per inner fold (cross_validation)


def _group_slices(design):
    """Column offset of each group in the design's flattened rows (cols order)."""
    if "slices" not in design.cache:
        out, start = {}, 0
        for g, c in design.cols.items():
            out[g] = slice(start, start + c.shape[-1])
            start += c.shape[-1]
        design.cache["slices"] = out
    return design.cache["slices"]


def _flat_rows(design):
    """(A (R n, K) of every group, y (R n,), valid (R n,)): row-major (row, joint) elements;
    valid = not speed-saturated (velocity_saturation)."""
    if "flat" not in design.cache:
        K = sum(c.shape[-1] for c in design.cols.values())
        A = np.concatenate(list(design.cols.values()), -1).reshape(-1, K)
        design.cache["flat"] = (A, design.y.reshape(-1), ~design.row_saturated.reshape(-1))
    return design.cache["flat"]


def design_rows(design: Design, transform: TimeLaw | None, groups: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(A (R n, k), y (R n,)) for `groups` with a model-side time law (None, ("shift", d) or
    ("lag", d)): with a law the columns of `groups` and the nominal torque move, the
    measurement stays (model_side_rows)."""
    if transform is None:
        A, y, _ = _flat_rows(design)
        sl = _group_slices(design)
        cols = [np.arange(sl[g].start, sl[g].stop) for g in groups]
        return A[:, np.concatenate(cols) if cols else np.zeros(0, int)], y
    moving = [g for g in groups if design.cols[g].shape[-1]]
    A, nominal = model_side_rows(design, moving, transform)
    y = (design.y + design.tau_hat_nominal - nominal).reshape(-1)
    return A.reshape(A.shape[0] * A.shape[1], A.shape[-1]), y


def design_normal(design: Design, transform: TimeLaw | None) -> tuple[np.ndarray, np.ndarray, float, int]:
    """(G, b, y'y, rows) of the valid elements of one design, every group, one time law:
    formed once per design and law (a time-law search revisits the same d across folds and
    effect sets) and summed over the logs of a fit."""
    key = ("normal", transform)
    if key not in design.cache:
        A, y = design_rows(design, transform, list(design.cols))
        valid = _flat_rows(design)[2]
        A, y = A[valid], y[valid]
        design.cache[key] = (A.T @ A, A.T @ y, float(y @ y), int(valid.sum()))
    return design.cache[key]


def design_residual(design: Design, params: Params) -> np.ndarray:
    """Residual (R, n) of one design on every element after the effects `params`
    ({group: array}; a TIME_LAWS group carries d). The one function that scores a set of
    effects on a log: selection (inner folds), the check logs and a frozen corrected model."""
    groups = [g for g in params if g not in TIME_LAWS]
    timed = [g for g in params if g in TIME_LAWS]
    transform = (TIME_LAWS[timed[0]], float(params[timed[0]][0])) if timed else None
    A, y = design_rows(design, transform, groups)
    p = np.concatenate([params[g] for g in groups]) if groups else np.zeros(0)
    return (y - A @ p).reshape(design.y.shape)


class Problem:
    """Fit designs (their normal equations, summed) and check designs (scored element-wise)."""

    def __init__(self, model: RobotModel, fit: list[Design], check: list[Design]) -> None:
        self.model = model
        self.fit, self.check = list(fit), list(check)
        self.groups = list(fit[0].cols)
        self.k = {g: fit[0].cols[g].shape[-1] for g in self.groups}
        self.offset = {}
        start = 0
        for g in self.groups:
            self.offset[g] = start
            start += self.k[g]
        self.K = start
        n = fit[0].y.shape[1]
        self.n = n
        # Rows where a joint is speed-saturated obey no model (velocity_saturation): fitting and
        # selection use the valid elements only; reports also give the all-sample residual.
        G, b, yy, rows = design_normal(fit[0], None)
        for d in fit[1:]:
            Gd, bd, yyd, rd = design_normal(d, None)
            G, b, yy, rows = G + Gd, b + bd, yy + yyd, rows + rd
        self.G, self.b, self.yy, self.n_fit_rows = G, b, yy, rows
        self.check_valid = np.concatenate([_flat_rows(d)[2] for d in check]) if check else np.zeros(0, bool)
        self.y_check_all = np.concatenate([d.y.reshape(-1) for d in check]) if check else np.zeros(0)
        self.y_check = self.y_check_all[self.check_valid]
        # Row-major flattening: element (row, joint); blocks numbered across check logs.
        blocks, base = [], 0
        for d in check:
            blocks.append(np.repeat(d.row_block + base, n))
            base += d.row_block.max() + 1
        self.check_block = np.concatenate(blocks)[self.check_valid] if check else np.zeros(0, int)
        self.check_joint = np.tile(np.arange(n), len(self.y_check_all) // n)[self.check_valid]
        tau_check = np.concatenate([d.y + d.tau_hat_nominal for d in check]) if check else np.zeros((1, n))
        self.tau_rms_check = np.sqrt(np.mean(tau_check**2, 0))
        self.min_delay = 0.5 * float(np.median(np.concatenate([np.diff(d.sample["t"]) for d in fit])))

    def index(self, groups: list[str]) -> np.ndarray:
        return (
            np.concatenate([np.arange(self.offset[g], self.offset[g] + self.k[g]) for g in groups])
            if groups
            else np.zeros(0, int)
        )

    def _system(self, transform, groups):
        """(G, b, yy) of the fit logs for `groups` (column order of index(groups)) with a model
        side time law (None: none), summed from the designs' cached normal equations."""
        idx = self.index(groups)
        if transform is None:
            return self.G[np.ix_(idx, idx)], self.b[idx], self.yy
        G, b, yy, _ = design_normal(self.fit[0], transform)
        for d in self.fit[1:]:
            Gd, bd, yyd, _ = design_normal(d, transform)
            G, b, yy = G + Gd, b + bd, yy + yyd
        return G[np.ix_(idx, idx)], b[idx], yy

    def fit_effects(self, effects: list[str]) -> tuple[Params, float]:
        return fit_effects(self, effects)

    def solve(self, groups: list[str]) -> tuple[Params, float]:
        """Constrained least squares on the fit logs for the union of `groups`.

        A time law (TIME_LAWS: pure delay or first-order lag of the model side) is a 1-D search
        on a DELAY_FINE_S grid around the linear estimate of the lag law (-d dtau_meas/dt, which
        only says where to look), extended while the best d sits at an end of the grid; only
        smooth model rows move, never the noisy measurement.
        Returns (params dict group -> array, fit SSE)."""
        timed = [g for g in groups if g in TIME_LAWS]
        if not timed:
            return self._solve_linear(groups, None)
        (time_group,) = timed
        law = TIME_LAWS[time_group]
        others = [g for g in groups if g != time_group]
        estimate = self._solve_linear(others + ["time_delay"], None, consistent=False)[0]["time_delay"][0]
        centre = DELAY_FINE_S * round(float(estimate) / DELAY_FINE_S)
        lowest = -MAX_DELAY_S if law == "shift" else DELAY_FINE_S  # a lag has d > 0
        errs = {}

        def scan(ds):
            for d in np.unique(np.clip(np.round(ds, 6), lowest, MAX_DELAY_S)):
                if float(d) not in errs:
                    errs[float(d)] = self._solve_linear(others, (law, float(d)), consistent=False)[1]

        steps = DELAY_FINE_S * np.arange(1, 7)
        scan(centre + np.r_[-steps[::-1], 0.0, steps])
        # The linear estimate only says where to look: walk on while the best is at an end.
        while True:
            grid = np.array(sorted(errs))
            best = min(errs, key=errs.get)
            if best == grid[-1] and best < MAX_DELAY_S:
                scan(best + steps)
            elif best == grid[0] and best > lowest:
                scan(best - steps)
            else:
                break
        # Between grid points: the vertex of the parabola through the best point and its
        # neighbours (SSE is smooth in d), kept when it fits better.
        i = int(np.searchsorted(grid, best))
        if 0 < i < len(grid) - 1:
            (d0, d1, d2) = grid[i - 1 : i + 2]
            e0, e1, e2 = errs[float(d0)], errs[float(d1)], errs[float(d2)]
            curvature = e0 - 2 * e1 + e2
            if curvature > 0:
                vertex = float(np.round(d1 + 0.5 * DELAY_FINE_S * (e0 - e2) / curvature, 3))  # 1 ms: reused
                errs[vertex] = self._solve_linear(others, (law, vertex), consistent=False)[1]
                best = min(errs, key=errs.get)
        params, err = self._solve_linear(others, (law, best))
        params = dict(params)
        params[time_group] = np.array([best])
        return {g: params[g] for g in groups}, err

    def _solve_linear(self, groups, transform, consistent=True):
        from scipy.optimize import lsq_linear

        G, b, yy = self._system(transform, groups)
        idx = self.index(groups)
        if len(idx) == 0:
            return {}, yy
        s = np.sqrt(np.diag(G))
        s[s <= 1e-12 * max(s.max(), 1e-300)] = 1.0
        Gs = G / np.outer(s, s)
        bs = b / s
        jitter = 1e-10 * np.trace(Gs) / len(idx)
        R = np.linalg.cholesky(Gs + jitter * np.eye(len(idx))).T
        z = np.linalg.solve(R.T, bs)
        lo, hi = [], []
        for g in groups:
            l, h = group_bounds(self.model, g, self.k[g])
            lo.append(l)
            hi.append(h)
        lo, hi = np.concatenate(lo) * s, np.concatenate(hi) * s
        if np.all(np.isinf(lo)) and np.all(np.isinf(hi)):
            ps = np.linalg.solve(R, z)
        else:
            ps = lsq_linear(R, z, bounds=(lo, hi), method="bvls", tol=1e-12).x
        p = ps / s
        if "payload" in groups and consistent:
            p = self._consistent_payload(groups, idx, p, R, z, s, lo, hi)
        sse = yy - 2 * p @ b + p @ G @ p
        out, pos = {}, 0
        for g in groups:
            out[g] = p[pos : pos + self.k[g]]
            pos += self.k[g]
        return out, max(float(sse), 0.0)

    def _consistent_payload(self, groups, idx, p, R, z, s, lo, hi):
        """Re-fit with theta_e0 + dtheta = P(eta) (log-Cholesky) when the linear fit is not
        physically consistent; other parameters keep their bounds."""
        from scipy.optimize import least_squares

        pos = 0
        for g in groups:
            if g == "payload":
                break
            pos += self.k[g]
        sl = slice(pos, pos + 10)
        theta_e0 = self.model.theta_e
        total = theta_e0 + p[sl]
        if p[sl][0] >= -1e-12 and inertial.is_physically_consistent(total, 1e-9):
            return p
        # Start: nominal end effector (plus a tiny sphere so the pseudo-inertia is invertible).
        start = theta_e0 + inertial.from_mass_com_inertia(1e-3, np.zeros(3), 1e-6 * np.eye(3))
        try:
            eta0 = inertial.theta_to_log_cholesky(start)
        except ValueError:
            eta0 = inertial.theta_to_log_cholesky(inertial.from_mass_com_inertia(1e-2, np.zeros(3), 1e-5 * np.eye(3)))
        others = np.ones(len(p), bool)
        others[sl] = False
        x0 = np.concatenate([eta0, np.clip(p[others] * s[others], lo[others], hi[others])])
        lo_x = np.concatenate([np.full(10, -np.inf), lo[others]])
        hi_x = np.concatenate([np.full(10, np.inf), hi[others]])
        eps = 1e-12
        x0 = np.clip(x0, lo_x + eps * (np.isfinite(lo_x)), hi_x - eps * (np.isfinite(hi_x)))

        def unpack(x):
            full = np.empty(len(p))
            full[sl] = (inertial.log_cholesky_to_theta(x[:10]) - theta_e0) * s[sl]
            full[others] = x[10:]
            return full

        def res(x):
            return R @ unpack(x) - z

        def jac(x):
            J = np.empty((len(z), len(x)))
            J[:, :10] = (R[:, sl] * s[sl]) @ inertial.log_cholesky_jacobian(x[:10])
            J[:, 10:] = R[:, others]
            return J

        with np.errstate(over="ignore", invalid="ignore"):
            sol = least_squares(res, x0, jac=jac, bounds=(lo_x, hi_x), method="trf", x_scale="jac", max_nfev=60)
        q = unpack(sol.x) / s
        if not np.all(np.isfinite(q)):  # solver failure: safe fallback, no payload change
            q = np.where(np.isfinite(q), q, 0.0)
            q[sl] = 0.0
        if q[sl][0] < 0:  # the payload must not remove mass: fall back to no payload change
            q[sl] = 0.0
        return q

    def check_residual(self, params: Params, valid_only: bool = True) -> np.ndarray:
        """Check residual flattened row-major, on the valid (not speed-saturated) elements or on
        every element."""
        if not self.check:
            return np.zeros(0)
        r = np.concatenate([design_residual(d, params).reshape(-1) for d in self.check])
        return r[self.check_valid] if valid_only else r

    def check_residual_all(self, params: Params) -> np.ndarray:
        return self.check_residual(params, valid_only=False)

    def fit_residual(self, params: Params) -> np.ndarray:
        r = [design_residual(d, params).reshape(-1)[_flat_rows(d)[2]] for d in self.fit]
        return np.concatenate(r)


def fit_effects(problem: Problem, effects: list[str]) -> tuple[Params, float]:
    """Best fit of a set of effects (Stribeck: the grid velocity with the lowest fit SSE)."""
    options = [[]]
    for e in effects:
        options = [o + [g] for o in options for g in effect_groups(e)]
    best = None
    for groups in options:
        params, sse = problem.solve(groups)
        if best is None or sse < best[1]:
            best = (params, sse)
    return best


def n_params(params: Params | FoldParams) -> int:
    """Free parameters of a fit (of one fold's fit for inner folds: a tuple of dicts)."""
    if isinstance(params, tuple):
        return n_params(params[0]) if params else 0
    return sum(len(p) for p in params.values())
