"""Frozen scoring: the one code path for check logs and for a corrected_model.yaml (nothing is
fitted; residual RMS before/after overall, per joint and per log).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from safesysid.systems.model.corrected_model import (
    CorrectedEffect,
    CorrectedModel,
    CorrectedModelError,
    Saturation,
    Scoring,
    group_params,
)
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.robot_model import RobotModel

from .design import WINDOW_S, Design, build_design, rms, velocity_saturation
from .effects import STRIBECK_VELOCITIES, Params, effect_params, group_of
from .problem import design_residual
from .selection import Selection

# ---- frozen scoring: the one code path for check logs and for a corrected_model.yaml ---------


def frozen_designs(
    model: RobotModel, logs: Sequence[JointLog], form: str, rule: Saturation | None, *, window_s: float = WINDOW_S
) -> list[Design]:
    """Designs of logs scored with a frozen rule: the residual form of the diagnosis (the
    momentum form when a log has no accelerations) and the speed-saturation rule of the fit
    logs (None: nothing flagged)."""
    if form == "inverse_dynamics" and any(l.a is None for l in logs):
        form = "momentum"
    masks = velocity_saturation(logs, rule) if rule is not None else [np.zeros(l.v.shape, bool) for l in logs]
    return [build_design(model, l, form, window_s=window_s, saturated=m) for l, m in zip(logs, masks)]


def score_designs(corrected: CorrectedModel, designs: list[Design]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(before, after): residual (R, n) per design of the nominal model and of the frozen
    corrected model (corrected_model.CorrectedModel). Fits nothing."""
    params = group_params(corrected.effects)
    for k, e in enumerate(corrected.effects):
        if e.name == "stribeck_friction" and f"stribeck_friction@{float(e.params['vs_rad_s'])}" not in designs[0].cols:
            raise CorrectedModelError(
                f"{corrected.path or 'corrected model'}: effects[{k}].params.vs_rad_s: "
                f"{e.params['vs_rad_s']} is not one of {', '.join(map(str, STRIBECK_VELOCITIES))}"
            )
    return [d.y for d in designs], [design_residual(d, params) for d in designs]


def score(
    model: RobotModel, corrected: CorrectedModel, logs: Sequence[JointLog]
) -> tuple[list[Design], list[np.ndarray], list[np.ndarray], dict]:
    """Score a frozen corrected model on logs (`diagnose --model corrected_model.yaml --check`):
    (designs, before, after, held_out_numbers)."""
    sc = corrected.scoring
    designs = frozen_designs(model, logs, sc.residual_form, sc.saturation, window_s=sc.window_s)
    before, after = score_designs(corrected, designs)
    return designs, before, after, held_out_numbers(designs, before, after)


def rms_table(before: np.ndarray, after: np.ndarray, mask: np.ndarray) -> dict:
    """RMS before/after and reduction, overall and per joint, over the elements in `mask`."""
    n = before.shape[1]
    b = [rms(before[mask[:, j], j]) if mask[:, j].any() else 0.0 for j in range(n)]
    a = [rms(after[mask[:, j], j]) if mask[:, j].any() else 0.0 for j in range(n)]
    rb, ra = (rms(before[mask]), rms(after[mask])) if mask.any() else (0.0, 0.0)
    return {
        "rms_before": rb,
        "rms_after": ra,
        "reduction": reduction(rb, ra),
        "rms_before_per_joint": b,
        "rms_after_per_joint": a,
        "reduction_per_joint": [reduction(x, y) for x, y in zip(b, a)],
    }


def held_out_numbers(designs: list[Design], before: list[np.ndarray], after: list[np.ndarray]) -> dict:
    """Residual RMS before/after on scored logs: every element (contract meaning) and without
    the speed-saturated ones, overall, per joint and per log."""
    b, a = np.concatenate(before), np.concatenate(after)
    valid = ~np.concatenate([d.row_saturated for d in designs])
    out = rms_table(b, a, np.ones_like(valid))
    out["without_saturated"] = rms_table(b, a, valid)
    out["logs"] = [d.source for d in designs]
    out["rms_before_per_log"] = [rms(x) for x in before]
    out["rms_after_per_log"] = [rms(x) for x in after]
    out["residual_form"] = designs[0].form
    return out


def corrected_model_of(
    model: RobotModel,
    selection: Selection,
    params: Params,
    form: str,
    rule: Saturation,
    *,
    model_path: str | Path = "",
    fit_sources: Sequence[str] = (),
) -> CorrectedModel:
    """CorrectedModel of a diagnosis: the starting model, the selected effects (most important
    first) with their parameters refitted on all fit logs, and the frozen scoring rule."""
    path = str(model_path or model.source or "")
    effects = [
        CorrectedEffect(e, list(selection.joints[e]), effect_params(model, e, params, group_used=group_of(e, params)))
        for e in selection.effects
    ]
    return CorrectedModel(
        path,
        effects,
        Scoring(form, WINDOW_S, rule),
        str(Path(path).resolve()) if path else "",
        [str(s) for s in fit_sources],
    )


def reduction(before: float, after: float) -> float:
    return float(np.clip(1.0 - after / before, 0.0, 1.0)) if before > 0 else 0.0
