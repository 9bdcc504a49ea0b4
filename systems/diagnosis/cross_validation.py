"""Inner folds on the fit logs (the honest protocol's selection data): leave one fit log out,
or contiguous time pieces when there is one fit log.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from safesysid.systems.model.corrected_model import Saturation
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.robot_model import RobotModel

from .design import WINDOW_S, Design, build_design, velocity_saturation
from .problem import FoldParams, Problem, fit_effects

TIME_FOLDS = 3  # inner folds (contiguous pieces in time) when there is a single fit log


# ---- the honest protocol: select on inner folds of the fit logs, score the check logs once --
class CrossValidated:
    """Selection data of the honest protocol: inner folds on the fit logs only. Each fold fits
    on its training designs and is scored on its validation designs; every fit-log element is
    validated exactly once, so the concatenated validation residuals carry the significance
    tests, the best single/pair, the greedy additions and the per-joint assignment. Parameters
    are one dict per fold (a tuple)."""

    def __init__(
        self, model: RobotModel, designs: list[Design], folds: list[tuple[list[int], list[int]]], *, scheme: str
    ) -> None:
        self.designs, self.folds, self.scheme = designs, folds, scheme
        self.problems = [Problem(model, [designs[i] for i in tr], [designs[i] for i in va]) for tr, va in folds]
        self.n = model.n
        self.empty = tuple({} for _ in folds)
        self.y_check = np.concatenate([p.y_check for p in self.problems])
        self.y_check_all = np.concatenate([p.y_check_all for p in self.problems])
        self.check_valid = np.concatenate([p.check_valid for p in self.problems])
        blocks, base = [], 0
        for p in self.problems:
            blocks.append(p.check_block + base)
            base += int(p.check_block.max()) + 1 if len(p.check_block) else 0
        self.check_block = np.concatenate(blocks)
        self.check_joint = np.concatenate([p.check_joint for p in self.problems])
        tau = np.concatenate([d.y + d.tau_hat_nominal for p in self.problems for d in p.check])
        self.tau_rms_check = np.sqrt(np.mean(tau**2, 0))
        self.n_fit_rows = sum(p.n_fit_rows for p in self.problems)
        self.yy = sum(p.yy for p in self.problems)
        self.min_delay = min(p.min_delay for p in self.problems)

    def fit_effects(self, effects: list[str]) -> tuple[FoldParams, float]:
        """Per-fold fits (tuple of params) and their summed training SSE."""
        fits = [fit_effects(p, effects) for p in self.problems]
        return tuple(f[0] for f in fits), float(sum(f[1] for f in fits))

    def check_residual(self, params: FoldParams, valid_only: bool = True) -> np.ndarray:
        """Validation residual of every fold, concatenated (flattened row-major)."""
        return np.concatenate([p.check_residual(q, valid_only) for p, q in zip(self.problems, params)])


def time_pieces(t: np.ndarray, k: int = TIME_FOLDS) -> list[slice]:
    """k contiguous index slices of equal duration."""
    edges = np.searchsorted(t, t[0] + (t[-1] - t[0]) * np.arange(1, k) / k)
    bounds = np.concatenate([[0], edges, [len(t)]])
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def inner_folds(model: RobotModel, fit_logs: list[JointLog], form: str, *, rule: Saturation) -> CrossValidated:
    """CrossValidated on the fit logs: leave one fit log out, or time-blocked folds (TIME_FOLDS
    contiguous pieces, leave one piece out) when there is one fit log."""
    masks = velocity_saturation(fit_logs, rule)
    if len(fit_logs) >= 2:
        designs = [build_design(model, l, form, window_s=WINDOW_S, saturated=m) for l, m in zip(fit_logs, masks)]
        scheme = "leave_one_fit_log_out"
    else:
        (log,), (mask,) = fit_logs, masks
        designs = []
        for sl in time_pieces(log.t):
            piece = dataclasses.replace(
                log.slice(sl), source=f"{log.source} [{log.t[sl][0]:.2f}, {log.t[sl][-1]:.2f}] s"
            )
            designs.append(build_design(model, piece, form, window_s=WINDOW_S, saturated=mask[sl]))
        scheme = "time_blocked"
    folds = [([i for i in range(len(designs)) if i != k], [k]) for k in range(len(designs))]
    return CrossValidated(model, designs, folds, scheme=scheme)
