"""The diagnosis self-check (`safesysid diagnose --self-check`): blind diagnosis of simulated
cases (diagnosis/simulate.py) with withheld effects, scored against the truth.

Honest like the diagnosis: each case has two fit logs, on which all selection happens (inner
cross-validation), and one check log, scored once. Named effects are compared with the truth by
name (confusion table) and by value (value_errors: delay, friction, armature, offset, payload
mass and CoM, tilt, stiffness). detection_limits finds, per effect, the smallest physical size
named in >= 90 % of cases at a given noise level.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from ..blas import single_threaded_blas
from ..robot_model import RobotModel
from .diagnose import diagnose
from .effects import EFFECTS, PER_JOINT
from .simulate import SNR_RANGE, make_case

NEAR_FLOOR_SNR = (1.0, 1.3)  # "close to the noise floor": effect RMS about the noise RMS


def case_plan(n_cases: int, rng: np.random.Generator, effects: Sequence[str] = EFFECTS) -> list[dict]:
    """Injected effect sets: every 5th case null, then alternating single and double effects;
    every other double puts two per-joint effects on the same joints; every 3rd non-null case
    is drawn close to the noise floor (NEAR_FLOOR_SNR); accelerations logged in every other
    case of each kind."""
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
        )
        d = diagnose(model, fit, check)
    named = d.result["cause"]
    inj = spec["injected"]
    fitted = {e["name"]: e["params"] for e in d.result["effects"] if e["significant"]}
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
    }
    if "time_delay" in inj and "time_delay" in named:  # the right time law?
        case["time_law"] = {
            "injected": truth["effects"]["time_delay"]["params"].get("law", "shift"),
            "named": fitted["time_delay"]["time_law"],
        }
    return case


def parallel_map(fn: Callable[[Any], Any], jobs: Sequence, workers: int) -> Iterator:
    """fn over jobs, in `workers` processes when > 1 (results in job order)."""
    if workers <= 1:
        yield from map(fn, jobs)
        return
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(workers) as pool:
        yield from pool.map(fn, jobs)


def run_self_check(
    model: RobotModel, n_cases: int, seed: int, progress: Callable[[dict], None] | None = None, workers: int = 1
) -> tuple[list[dict], dict, dict]:
    """Blind diagnosis of simulated cases (selection on the fit logs only, the check log scored
    once); returns (cases, summary, confusion)."""
    plan = case_plan(n_cases, np.random.default_rng(seed))
    cases = []
    for case in parallel_map(_run_case, [(model, seed, i, spec) for i, spec in enumerate(plan)], workers):
        cases.append(case)
        if progress:
            progress(case)
    return cases, summarize(cases), confusion(cases)


# ---- parameter values against the withheld truth --------------------------------------------
def value_errors(name: str, truth: dict, fitted: dict) -> list[dict]:
    """Errors of a named effect's fitted parameters against the withheld truth: a list of
    {effect, quantity, unit, truth, fitted, abs_error, rel_error} (per-joint effects: on each
    injected joint the effect acts on, i.e. changes the torque by >= 20 % of its largest
    change; an elasticity on an axis whose torque does not depend on its angle is invisible
    and has no value to recover). rel_error is relative to the injected size."""
    tp = truth["params"]
    joints = [j - 1 for j in truth["injected_joints"] if j in truth.get("joints", truth["injected_joints"])]

    def rec(quantity, unit, t, f, size=None):
        size = abs(t) if size is None else size
        err = abs(f - t)
        return {
            "effect": name,
            "quantity": quantity,
            "unit": unit,
            "truth": float(t),
            "fitted": float(f),
            "abs_error": float(err),
            "rel_error": float(err / size) if size > 0 else None,
        }

    per_joint = {
        "coulomb_friction": ("delta", "delta_Fc_Nm", "ΔFc", "N·m"),
        "viscous_friction": ("delta", "delta_Fv_Nms_rad", "ΔFv", "N·m·s/rad"),
        "stribeck_friction": ("delta", "Fs_Nm", "Fs", "N·m"),
        "armature": ("delta", "delta_Ia_kgm2", "ΔIa", "kg·m²"),
        "torque_offset": ("delta", "offset_Nm", "offset", "N·m"),
        "load_friction": ("mu", "mu", "μ", "-"),
    }
    if name in per_joint:
        tk, fk, q, unit = per_joint[name]
        return [rec(q, unit, tp[tk][j], fitted[fk][j]) for j in joints]
    if name == "torque_scale":
        return [rec("scale", "-", tp["scale"][j], fitted["scale"][j], abs(tp["scale"][j] - 1.0)) for j in joints]
    if name == "joint_elasticity":
        return [
            r
            for j in joints
            for r in (
                rec(
                    "stiffness",
                    "N·m/rad",
                    1.0 / tp["compliance"][j],
                    1.0 / max(fitted["compliance_rad_per_Nm"][j], 1e-12),
                ),
                rec("compliance", "rad/(N·m)", tp["compliance"][j], fitted["compliance_rad_per_Nm"][j]),
            )
        ]
    if name == "time_delay":
        return [rec("d", "s", tp["delay_s"], fitted["delay_s"])]
    if name == "payload":
        m = tp["mass_kg"]
        com = np.asarray(tp["theta"][1:4]) / m
        err = float(np.linalg.norm(np.asarray(fitted["com_m"]) - com))
        return [
            rec("mass", "kg", m, fitted["mass_kg"]),
            {
                "effect": name,
                "quantity": "CoM",
                "unit": "m",
                "truth": float(np.linalg.norm(com)),
                "fitted": float(np.linalg.norm(fitted["com_m"])),
                "abs_error": err,
                "rel_error": err / float(np.linalg.norm(com)),
            },
        ]
    if name == "base_tilt":
        roll, pitch = tp["roll_pitch_rad"]
        size = max(abs(roll), abs(pitch))
        return [
            rec("roll", "rad", roll, fitted["roll_rad"], size),
            rec("pitch", "rad", pitch, fitted["pitch_rad"], size),
        ]
    return []


def error_table(cases: list[dict]) -> list[dict]:
    """Per effect and quantity: count, median and 90th percentile of the absolute and the
    relative error of the named injected effects."""
    rows = {}
    for c in cases:
        for e in c.get("value_errors", []):
            rows.setdefault((e["effect"], e["quantity"], e["unit"]), []).append(e)
    out = []
    for (effect, quantity, unit), recs in rows.items():
        ab = np.array([r["abs_error"] for r in recs])
        rel = np.array([r["rel_error"] for r in recs if r["rel_error"] is not None])
        out.append(
            {
                "effect": effect,
                "quantity": quantity,
                "unit": unit,
                "n": len(recs),
                "abs_median": float(np.median(ab)),
                "abs_p90": float(np.quantile(ab, 0.9)),
                "rel_median": float(np.median(rel)) if len(rel) else None,
                "rel_p90": float(np.quantile(rel, 0.9)) if len(rel) else None,
            }
        )
    order = {e: k for k, e in enumerate(EFFECTS)}
    return sorted(out, key=lambda r: (order[r["effect"]], r["quantity"]))


def error_markdown(table: list[dict]) -> str:
    lines = [
        "| effect | quantity | named cases·joints | median abs error | 90th pct abs error | median rel error "
        "| 90th pct rel error |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in table:
        rel = lambda x: "-" if x is None else f"{100 * x:.1f} %"  # noqa: E731
        lines.append(
            f"| {r['effect']} | {r['quantity']} [{r['unit']}] | {r['n']} | {r['abs_median']:.3g} "
            f"| {r['abs_p90']:.3g} | {rel(r['rel_median'])} | {rel(r['rel_p90'])} |"
        )
    return "\n".join(lines)


def summarize(cases: list[dict]) -> dict:
    n_inj = sum(len(c["injected"]) for c in cases)
    n_found = sum(len(c["injected"]) - len(c["missed"]) for c in cases)
    n_named = sum(len(c["named"]) for c in cases)
    n_false = sum(len(c["false"]) for c in cases)
    nulls = [c for c in cases if not c["injected"]]
    return {
        "cases": len(cases),
        "injected_effects": n_inj,
        "injected_named": n_found,
        "injected_named_rate": n_found / n_inj if n_inj else 1.0,
        "named_effects": n_named,
        "false_effects": n_false,
        "false_effect_rate": n_false / n_named if n_named else 0.0,
        "cases_with_false_effect": sum(bool(c["false"]) for c in cases),
        "cases_with_false_effect_rate": sum(bool(c["false"]) for c in cases) / len(cases) if cases else 0.0,
        "null_cases": len(nulls),
        "null_correct": sum(not c["named"] for c in nulls),
        "exact_cases": sum(not c["missed"] and not c["false"] for c in cases),
        "time_law_named": sum("time_law" in c for c in cases),
        "time_law_correct": sum(c["time_law"]["injected"] == c["time_law"]["named"] for c in cases if "time_law" in c),
        "missed": [
            {"case": c["case"], "effect": e, "snr": c["truth"]["effects"][e]["snr"]} for c in cases for e in c["missed"]
        ],
        "near_floor": _named_rate([c for c in cases if c.get("near_floor")]),
        "same_joints": _named_rate([c for c in cases if c.get("same_joints")]),
        "parameter_errors": error_table(cases),
    }


def _named_rate(cases):
    inj = sum(len(c["injected"]) for c in cases)
    found = sum(len(c["injected"]) - len(c["missed"]) for c in cases)
    return {
        "cases": len(cases),
        "injected_effects": inj,
        "injected_named": found,
        "cases_with_false_effect": sum(bool(c["false"]) for c in cases),
    }


def confusion(cases: list[dict], effects: Sequence[str] = EFFECTS) -> dict[str, dict[str, int]]:
    """counts[injected][named]. Per case and injected effect: its own column when named, else
    'none' (missed); every falsely named effect is counted in the row of each injected effect
    of that case (or the 'none' row for a null case). A null case naming nothing counts
    [none][none]. A second injected effect that is named is not a confusion, so it is not
    counted in the other effect's row."""
    labels = list(effects) + ["none"]
    table = {r: {c: 0 for c in labels} for r in labels}
    for c in cases:
        rows = c["injected"] or ["none"]
        for r in rows:
            if r != "none":
                table[r][r if r in c["named"] else "none"] += 1
            for f in c["false"]:
                table[r][f] += 1
            if r == "none" and not c["false"]:
                table["none"]["none"] += 1
    return table


def confusion_markdown(table: dict[str, dict[str, int]]) -> str:
    labels = list(table)
    short = {e: "".join(w[0] for w in e.split("_")) if e != "none" else "none" for e in labels}
    head = "| injected \\ named | " + " | ".join(short[c] for c in labels) + " |"
    sep = "|---" * (len(labels) + 1) + "|"
    rows = [
        f"| {r} | " + " | ".join(str(table[r][c]) if table[r][c] else "." for c in labels) + " |"
        for r in labels
        if any(table[r].values())
    ]
    key = "Columns: " + ", ".join(f"{short[e]} = {e}" for e in labels)
    return "\n".join([head, sep, *rows, "", key])
