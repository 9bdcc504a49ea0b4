"""The diagnosis: select on inner folds of the fit logs, refit on all of them, score the check
logs once; or score a frozen corrected model; or hold each log out once.

folds on them (leave one fit log out; TIME_FOLDS contiguous time pieces when there is one fit
log) fit each candidate set on the training folds and score it on the validation fold; the
validation residuals, concatenated (each fit-log sample validated once), are what the rules
below call "held-out". The speed-saturation top speeds come from the fit logs too. The selected
set is refitted on all fit logs; the check logs are scored once with that frozen selection and
its parameters (`test`), through design_residual, the function that also scores a
corrected_model.yaml (score).

"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from safesysid.systems.math.blas import single_threaded_blas
from safesysid.systems.model.corrected_model import CorrectedModel, group_params
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.robot_model import RobotModel

from .cross_validation import inner_folds
from .design import BLOCK_S, Design, choose_form, rms, saturation_rule
from .effects import EFFECTS, Params, corrected_parameters, effect_params, group_of
from .intervals import NOTE as INTERVALS_NOTE
from .intervals import statistical_intervals
from .problem import Problem, design_residual
from .report_data import held_out_result, residual_map
from .scoring import corrected_model_of, frozen_designs, held_out_numbers, reduction, rms_table, score, score_designs
from .selection import MIN_BLOCKS, MIN_EFFECT_RATIO, MIN_NOISE_FRACTION, MIN_RELATIVE, P_BLOCKS, Z_BLOCK, select_effects


@dataclass
class Diagnosis:
    result: dict  # diagnosis.json content
    form: str
    fit_designs: list[Design]
    check_designs: list[Design]
    check_residual_before: list[np.ndarray]  # per check log (R, n)
    check_residual_after: list[np.ndarray]
    combined_params: Params  # {group: array}, refitted on all fit logs
    corrected: dict  # corrected joint parameters and other effects for corrected_params.yaml
    corrected_model: CorrectedModel | None = None  # frozen selection + parameters


def diagnose(
    model: RobotModel,
    fit_logs: Sequence[JointLog],
    check_logs: Sequence[JointLog],
    *,
    effects: Sequence[str] = EFFECTS,
    form: str | None = None,
    max_effects: int = 6,
    model_path: str | Path = "",
) -> Diagnosis:
    """Diagnose the gap between `model` and logs; returns a Diagnosis (result = contract JSON).

    Honest protocol: every selection step and threshold uses the fit logs only (inner folds:
    leave one fit log out, time-blocked with one fit log); the parameters of the selected set
    are refitted on all fit logs and the check logs are scored once with them (`test`)."""
    with single_threaded_blas():
        return _diagnose(model, list(fit_logs), list(check_logs), effects, form, max_effects, model_path)


def _diagnose(model, fit_logs, check_logs, effects, form, max_effects, model_path):
    form = form or choose_form(fit_logs + check_logs)
    rule = saturation_rule(fit_logs)  # frozen on the fit logs
    cv = inner_folds(model, fit_logs, form, rule=rule)
    sel = select_effects(cv, effects, max_effects)
    check = frozen_designs(model, check_logs, form, rule)
    final = Problem(model, cv.designs, check)
    params, _ = final.fit_effects(sel.effects)
    intervals = statistical_intervals(model, final, params, effects=sel.effects)
    corrected_model = corrected_model_of(
        model, sel, params, form, rule, model_path=model_path, fit_sources=[l.source for l in fit_logs]
    )
    for e in corrected_model.effects:
        e.intervals = intervals[e.name]
    before, after = score_designs(corrected_model, check)
    test = held_out_numbers(check, before, after)
    n = model.n
    entries = _effect_entries(model, final, cv, sel, params=params, intervals=intervals, test=test, effects=effects)

    cv_before = cv.y_check_all.reshape(-1, n)
    cv_after = cv.check_residual(sel.params, valid_only=False).reshape(-1, n)
    cv_valid = cv.check_valid.reshape(-1, n)
    cross_validation = {
        "scheme": cv.scheme,
        "folds": [{"fit": [d.source for d in p.fit], "validate": [d.source for d in p.check]} for p in cv.problems],
        **rms_table(cv_before, cv_after, np.ones_like(cv_valid)),
        "without_saturated": rms_table(cv_before, cv_after, cv_valid),
        "selection": sel.steps,
    }
    result = held_out_result(check, before, after, test=test, entries=entries, form=form)
    result["gap"]["rms_fit"] = float(np.sqrt(final.yy / max(final.n_fit_rows, 1)))
    result["combined"].update(rms_fit_after=rms(final.fit_residual(params)), selection=sel.steps)
    result.update(
        {
            "test": {
                **test,
                "note": "check logs, scored once with the frozen selection and parameters; "
                "no selection step or threshold saw them",
            },
            "cross_validation": cross_validation,
            "intervals_note": INTERVALS_NOTE,
            "ambiguous": _ambiguous(final, sel),
            "unresolved": sel.unresolved,
            "protocol": {
                "selection_data": "fit logs only (inner cross-validation: " + cv.scheme + ")",
                "check_logs": "scored once (test)",
                "saturation_top_speed_rad_s": list(rule.top_speed_rad_s),
            },
            "significance_rule": {
                "z_block": Z_BLOCK,
                "p_blocks": P_BLOCKS,
                "min_blocks": MIN_BLOCKS,
                "block_s": BLOCK_S,
                "min_relative": MIN_RELATIVE,
                "min_effect_ratio": MIN_EFFECT_RATIO,
                "min_noise_fraction": MIN_NOISE_FRACTION,
                "information_criterion": "BIC on the inner training folds",
                "data": "validation residuals of the inner folds on the fit logs",
            },
        }
    )
    corrected = corrected_parameters(model, sel.effects, params)
    return Diagnosis(result, form, cv.designs, check, before, after, params, corrected, corrected_model)


def _effect_entries(model, final, cv, sel, *, params, intervals, test, effects):
    """diagnosis.json's entry per candidate effect (selected ones first, in selection order): its
    parameters (combined fit when selected, alone otherwise), check RMS alone and significance."""
    n = model.n
    entries = []
    for e in effects:
        alone, _ = final.fit_effects([e])
        rms_alone = rms(final.check_residual_all(alone))
        chosen = e in sel.effects
        src = params if chosen else alone
        entry = {
            "name": e,
            "joints": sel.joints[e] if chosen else _effect_joints_single(cv, sel.single[e]["params"], e, n),
            "params": effect_params(model, e, src, group_used=group_of(e, src)),
            "rms_check_after": rms_alone,
            "reduction": reduction(test["rms_before"], rms_alone),
            "significant": chosen,
            "params_from": "combined" if chosen else "alone",
            "test_alone": _json_sig(sel.single[e]["sig"]),
        }
        if chosen:
            entry["selection_step"] = sel.effects.index(e) + 1
            entry["intervals"] = intervals[e]
        entries.append(entry)
    entries.sort(key=lambda x: (not x["significant"], x.get("selection_step", 0), -x["test_alone"]["delta_mse"]))
    return entries


def frozen_diagnosis(model: RobotModel, corrected: CorrectedModel, logs: Sequence[JointLog]) -> Diagnosis:
    """Logs scored with a frozen corrected model (`diagnose --model corrected_model.yaml
    --check`): the contract fields on those logs, each effect's own numbers with that effect of
    the file alone; nothing is fitted or selected."""
    with single_threaded_blas():
        designs, before, after, test = score(model, corrected, logs)
        entries = []
        for k, e in enumerate(corrected.effects):
            rms_alone = rms(np.concatenate([design_residual(d, group_params([e])) for d in designs]))
            entries.append(
                {
                    "name": e.name,
                    "joints": list(e.joints),
                    "params": e.params,
                    "rms_check_after": rms_alone,
                    "reduction": reduction(test["rms_before"], rms_alone),
                    "significant": True,
                    "params_from": "frozen",
                    "selection_step": k + 1,
                }
            )
        result = held_out_result(designs, before, after, test=test, entries=entries, form=designs[0].form)
    sc = corrected.scoring
    result["gap"]["rms_fit"] = None  # no fit logs
    result["test"] = {**test, "note": "scored with the frozen corrected model; nothing fitted, nothing selected"}
    result["frozen"] = {
        "corrected_model": corrected.path,
        "model": str(corrected.model_path()),
        "fitted": "nothing",
        "residual_form": sc.residual_form,
        "saturation_top_speed_rad_s": sc.saturation.top_speed_rad_s if sc.saturation else None,
    }
    return Diagnosis(
        result, designs[0].form, [], designs, before, after, group_params(corrected.effects), {}, corrected
    )


def leave_one_out(model: RobotModel, logs: Sequence[JointLog], **kwargs: Any) -> tuple[list[Diagnosis], dict]:
    """Each log held out once, the effects selected and fitted on the others (nested: the
    held-out log is never seen by the inner selection): (fold Diagnoses, pooled)."""
    import time

    folds = []
    for held in range(len(logs)):
        t0 = time.perf_counter()
        folds.append(diagnose(model, [l for k, l in enumerate(logs) if k != held], [logs[held]], **kwargs))
        folds[-1].result["wall_time_s"] = time.perf_counter() - t0
    return folds, pool_held_out(folds)


def pool_held_out(folds: list[Diagnosis]) -> dict:
    """Held-out (test) numbers over folds that each check one log: RMS before/after pooled over
    all held-out samples (per joint and overall, all samples and without speed-saturated ones),
    the mean over folds (a per-run reduction), per fold, and the effects named in every fold."""
    before = np.concatenate([r for d in folds for r in d.check_residual_before])
    after = np.concatenate([r for d in folds for r in d.check_residual_after])
    valid = ~np.concatenate([c.row_saturated for d in folds for c in d.check_designs])
    per_fold = [
        {
            "check": [c.source for c in d.check_designs],
            "rms_before": d.result["gap"]["rms_check"],
            "rms_after": d.result["combined"]["rms_check_after"],
            "reduction": d.result["combined"]["reduction"],
            "without_saturated": d.result["combined"]["without_saturated"],
            "cause": d.result["cause"],
            "params": {e["name"]: e["params"] for e in d.result["effects"] if e["significant"]},
            "rms_before_per_joint": d.result["gap"]["rms_check_per_joint"],
            "rms_after_per_joint": d.result["combined"]["rms_check_per_joint_after"],
            "cross_validation": {
                k: d.result["cross_validation"][k] for k in ("scheme", "rms_before", "rms_after", "reduction")
            },
            "wall_time_s": d.result.get("wall_time_s"),
        }
        for d in folds
    ]
    mean_before = float(np.mean([f["rms_before"] for f in per_fold]))
    mean_after = float(np.mean([f["rms_after"] for f in per_fold]))
    causes = [set(f["cause"]) for f in per_fold]
    order = [e for f in per_fold for e in f["cause"]]
    every = set.intersection(*causes) if causes else set()
    some = set.union(*causes) if causes else set()
    return {
        "protocol": "nested: each held-out log scored once; selection on inner folds of the other logs",
        "pooled": rms_table(before, after, np.ones_like(valid)),
        "pooled_unsaturated": rms_table(before, after, valid),
        "saturated_share": float(1.0 - valid.mean()),
        "mean_over_folds": {
            "rms_before": mean_before,
            "rms_after": mean_after,
            "reduction": reduction(mean_before, mean_after),
        },
        "folds": per_fold,
        "named_in_every_fold": sorted(every, key=order.index),
        "named_in_some_fold": sorted(some - every, key=order.index),
        "residual_map_after": residual_map(
            [c for d in folds for c in d.check_designs], [r for d in folds for r in d.check_residual_after]
        ),
    }


def _ambiguous(final: Problem, sel) -> list[dict]:
    """The sets that explain the validation data as well as the named best pair (selection.
    equally_good), each beside the best with both scores (validation and check RMS) and the data
    that would separate them; empty when the choice is clear."""
    best = [s["effect"] for s in sel.steps if s.get("phase") == "best pair"]
    check_rms = lambda effects: rms(final.check_residual_all(final.fit_effects(list(effects))[0]))  # noqa: E731
    out = []
    for alt in sel.ambiguous:
        out.append(
            {
                "sets": [
                    {"effects": best, "rms_validation": alt["rms_validation_best"], "rms_check": check_rms(best)},
                    {
                        "effects": alt["effects"],
                        "rms_validation": alt["rms_validation"],
                        "rms_check": check_rms(alt["effects"]),
                    },
                ],
                "difference_z": alt["difference_z"],
                "separating_data": alt["separating_data"],
            }
        )
    return out


def _json_sig(sig):
    return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in sig.items()}


def _effect_joints_single(ev, params, e, n):
    """Joints an insignificant effect would touch most (for information only; validation data)."""
    r0 = ev.y_check
    r1 = ev.check_residual(params)
    gain = np.array([np.mean(r0[ev.check_joint == j] ** 2 - r1[ev.check_joint == j] ** 2) for j in range(n)])
    return [int(j) + 1 for j in np.argsort(-gain)[:3] if gain[j] > 0]
