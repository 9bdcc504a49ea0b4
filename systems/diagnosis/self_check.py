"""The diagnosis self-check (`safesysid diagnose --self-check`): blind diagnosis of simulated
cases (diagnosis/simulate.py) with withheld effects, scored against the truth.

Honest like the diagnosis: each case has two fit logs, on which all selection happens (inner
cross-validation), and one check log, scored once. Named effects are compared with the truth by
name (confusion table) and by value (value_errors: delay, friction, armature, offset, payload
mass and CoM, tilt, stiffness; truth_scores.py). detection_limits finds, per effect, the smallest physical size
named in >= 90 % of cases at a given noise level.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
from safesysid.systems.math.blas import single_threaded_blas
from safesysid.systems.model.robot_model import RobotModel

from .diagnose import Diagnosis, diagnose
from .effects import EFFECTS, PER_JOINT
from .intervals import CALIBRATION
from .simulate import SNR_RANGE, make_case
from .truth_scores import confusion, interval_coverage, summarize, value_errors

NEAR_FLOOR_SNR = (1.0, 1.3)  # "close to the noise floor": effect RMS about the noise RMS
HARD_NOISE_LEVEL = 0.03  # hard mode: the top of NOISE_LEVEL_RANGE in every case
BOOTSTRAP_EVERY = 4  # the block bootstrap's calibration check runs on every 4th case


def case_plan(
    n_cases: int, rng: np.random.Generator, *, effects: Sequence[str] = EFFECTS, hard: bool = False
) -> list[dict]:
    """Injected effect sets: every 5th case null, then alternating single and double effects;
    every other double puts two per-joint effects on the same joints; every 3rd non-null case
    is drawn close to the noise floor (NEAR_FLOOR_SNR); accelerations logged in every other
    case of each kind. hard: every non-null case has two effects, 3 % noise
    (HARD_NOISE_LEVEL) and no accelerations."""
    if hard:
        return _hard_plan(n_cases, rng, effects)
    plan, count = [], {0: 0, 1: 0, 2: 0}
    per_joint = [e for e in effects if e in PER_JOINT]
    non_null = 0
    for i in range(n_cases):
        same = False
        if i % 5 == 0:
            inj = []
        elif i % 2 == 1:
            inj = [effects[(i // 2) % len(effects)]]
        else:
            same = count[2] % 2 == 1 and len(per_joint) >= 2
            inj = [str(e) for e in rng.choice(per_joint if same else effects, size=2, replace=False)]
        near = bool(inj) and non_null % 3 == 2
        non_null += bool(inj)
        with_a = count[len(inj)] % 2 == 0  # alternate per kind: both forms for null/single/double
        count[len(inj)] += 1
        plan.append({"injected": inj, "with_acceleration": with_a, "same_joints": same, "near_floor": near})
    return plan


def _hard_plan(n_cases, rng, effects):
    """The hard mode of case_plan: every 5th case null, the others two distinct effects (every
    other pair of per-joint effects on the same joints), 3 % noise, no accelerations."""
    plan, doubles = [], 0
    per_joint = [e for e in effects if e in PER_JOINT]
    for i in range(n_cases):
        same = i % 5 != 0 and doubles % 2 == 1 and len(per_joint) >= 2
        inj = [] if i % 5 == 0 else [str(e) for e in rng.choice(per_joint if same else effects, size=2, replace=False)]
        doubles += bool(inj)
        plan.append(
            {
                "injected": inj,
                "with_acceleration": False,
                "same_joints": same,
                "near_floor": False,
                "noise_level": HARD_NOISE_LEVEL,
            }
        )
    return plan


def _run_case(job):
    """One blind case (a process-pool job): make the logs, diagnose on the fit logs, score the
    check log once, compare names and values with the withheld truth."""

    model, seed, i, spec = job
    crng = np.random.default_rng([seed, i])
    with single_threaded_blas():
        fit, check, truth = make_case(
            model,
            crng,
            spec["injected"],
            spec["with_acceleration"],
            snr_range=NEAR_FLOOR_SNR if spec["near_floor"] else SNR_RANGE,
            same_joints=spec["same_joints"],
            noise_level=spec.get("noise_level"),
        )
        d = diagnose(model, fit, check)
    named = d.result["cause"]
    inj = spec["injected"]
    fitted = {e["name"]: e["params"] for e in d.result["effects"] if e["significant"]}
    intervals = {e["name"]: e["intervals"] for e in d.result["effects"] if e["significant"]}
    case = {
        "case": i,
        **spec,
        "named": named,
        "form": d.form,
        "missed": [e for e in inj if e not in named],
        "false": [e for e in named if e not in inj],
        "truth": truth,
        "fitted": fitted,
        "rms_check": d.result["gap"]["rms_check"],
        "rms_check_after": d.result["combined"]["rms_check_after"],
        "cross_validation_reduction": d.result["cross_validation"]["reduction"],
        "joints_named": {e["name"]: e["joints"] for e in d.result["effects"] if e["significant"]},
        "value_errors": [err for e in inj if e in fitted for err in value_errors(e, truth["effects"][e], fitted[e])],
        "coverage": [
            rec for e in inj if e in fitted for rec in interval_coverage(e, truth["effects"][e], intervals[e])
        ],
    }
    case["ambiguous"] = [a["sets"][1]["effects"] for a in d.result["ambiguous"]]
    case["unresolved"] = d.result["unresolved"]  # not named: an equally good set lacks them
    case["interval_calibration"] = dict(CALIBRATION)  # what the recorded intervals were widened by
    if i % BOOTSTRAP_EVERY == 0 and named:
        case["bootstrap_over_sandwich"] = bootstrap_ratio(model, d, np.random.default_rng([seed, i, 1]))
    if "time_delay" in inj and "time_delay" in named:  # the right time law?
        case["time_law"] = {
            "injected": truth["effects"]["time_delay"]["params"].get("law", "shift"),
            "named": fitted["time_delay"]["time_law"],
        }
    return case


def bootstrap_ratio(model: RobotModel, d: Diagnosis, rng: np.random.Generator) -> float:
    """Median over the selected parameters of the block bootstrap's 90 % half-width (percentile)
    over the block sandwich's (intervals.py), on the diagnosis' fit logs: the calibration check
    of the Jacobian intervals, on a subset of cases (every BOOTSTRAP_EVERY-th)."""
    from .intervals import LEVEL, block_bootstrap, jacobian_rows, sandwich_covariance
    from .problem import Problem

    X, r, block = jacobian_rows(Problem(model, d.fit_designs, d.check_designs), d.combined_params)
    cov, ok = sandwich_covariance(X, r, block)
    draws = block_bootstrap(X, r, block, rng)
    boot = 0.5 * (np.quantile(draws, 0.5 + LEVEL / 2, 0) - np.quantile(draws, 0.5 - LEVEL / 2, 0))
    sand = 1.6449 * np.sqrt(np.maximum(np.diag(cov), 0.0))
    use = ok & (sand > 0)
    return float(np.median(boot[use] / sand[use])) if use.any() else 1.0


def parallel_map(fn: Callable[[Any], Any], jobs: Sequence, workers: int) -> Iterator:
    """fn over jobs, in `workers` processes when > 1 (results in job order)."""
    if workers <= 1:
        yield from map(fn, jobs)
        return
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(workers) as pool:
        yield from pool.map(fn, jobs)


def run_self_check(
    model: RobotModel,
    n_cases: int,
    seed: int,
    *,
    progress: Callable[[dict], None] | None = None,
    workers: int = 1,
    hard: bool = False,
) -> tuple[list[dict], dict, dict]:
    """Blind diagnosis of simulated cases (selection on the fit logs only, the check log scored
    once; hard: case_plan's hard mode); returns (cases, summary, confusion)."""
    plan = case_plan(n_cases, np.random.default_rng(seed), hard=hard)
    cases = []
    for case in parallel_map(_run_case, [(model, seed, i, spec) for i, spec in enumerate(plan)], workers):
        cases.append(case)
        if progress:
            progress(case)
    return cases, summarize(cases), confusion(cases)
