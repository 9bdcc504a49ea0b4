"""The self-check's scores against the withheld truth (self_check.py runs the cases): each named
effect's fitted values and intervals against the injected ones, coverage, spurious names, the
error and confusion tables and the summary."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from .effects import EFFECTS


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


# Per-joint values with an interval: (interval key, key of the injected truth in simulate.make_case).
TRUTH_OF = {
    "coulomb_friction": ("delta_Fc_Nm", "delta"),
    "viscous_friction": ("delta_Fv_Nms_rad", "delta"),
    "stribeck_friction": ("Fs_Nm", "delta"),
    "load_friction": ("mu", "mu"),
    "armature": ("delta_Ia_kgm2", "delta"),
    "torque_offset": ("offset_Nm", "delta"),
    "torque_scale": ("scale", "scale"),
    "joint_elasticity": ("compliance_rad_per_Nm", "compliance"),
}


def interval_coverage(name: str, truth: dict, intervals: dict) -> list[dict]:
    """Does each named injected value's statistical interval hold the withheld truth? A list of
    {effect, key, index, truth, lo, hi, covered} (per-joint effects: on the joints value_errors
    scores; payload: mass and each CoM coordinate; tilt: roll and pitch)."""
    tp = truth["params"]
    joints = [j - 1 for j in truth["injected_joints"] if j in truth.get("joints", truth["injected_joints"])]
    if name in TRUTH_OF:
        key, tkey = TRUTH_OF[name]
        values = [(key, j, tp[tkey][j]) for j in joints]
    elif name == "time_delay":
        values = [("delay_s", None, tp["delay_s"])]
    elif name == "payload":
        com = np.asarray(tp["theta"][1:4]) / tp["mass_kg"]
        values = [("mass_kg", None, tp["mass_kg"])] + [("com_m", k, com[k]) for k in range(3)]
    elif name == "base_tilt":
        values = [("roll_rad", None, tp["roll_pitch_rad"][0]), ("pitch_rad", None, tp["roll_pitch_rad"][1])]
    else:
        return []
    out = []
    for key, k, t in values:
        lo, hi = intervals[key] if k is None else (intervals[key][0][k], intervals[key][1][k])
        lo_f, hi_f = -np.inf if lo is None else lo, np.inf if hi is None else hi
        out.append(
            {
                "effect": name,
                "key": key,
                "index": k,
                "truth": float(t),
                "lo": lo,
                "hi": hi,
                "covered": bool(lo_f <= t <= hi_f),
            }
        )
    return out


def coverage_table(cases: list[dict]) -> dict:
    """Share of named injected values whose interval holds the truth: overall and per effect,
    and the number of cases that contributed."""
    recs = [r for c in cases for r in c.get("coverage", [])]
    boot = [c["bootstrap_over_sandwich"] for c in cases if "bootstrap_over_sandwich" in c]
    per = {}
    for r in recs:
        per.setdefault(r["effect"], []).append(r["covered"])
    return {
        "values": len(recs),
        "cases": sum(bool(c.get("coverage")) for c in cases),
        "covered": sum(r["covered"] for r in recs),
        "rate": float(np.mean([r["covered"] for r in recs])) if recs else None,
        "per_effect": {e: {"values": len(v), "rate": float(np.mean(v))} for e, v in per.items()},
        "bootstrap_over_sandwich_median": float(np.median(boot)) if boot else None,
        "bootstrap_cases": len(boot),
    }


def _needed_factor(rec: dict, case: dict) -> float:
    """Factor by which the raw (uncalibrated) sandwich interval of a coverage record must widen
    (about the fitted value, from the case's `fitted` params) to hold the truth: the widening
    the recorded interval needs, times the calibration factor the case ran with (none recorded:
    1)."""
    value = case["fitted"][rec["effect"]][rec["key"]]
    t, f = rec["truth"], value if rec["index"] is None else value[rec["index"]]
    end = rec["hi"] if t >= f else rec["lo"]
    if end is None:  # unbounded on that side
        return 0.0
    side = abs(end - f)
    ran_with = case.get("interval_calibration", {}).get(rec["effect"], 1.0)
    return ran_with * abs(t - f) / side if side > 0 else (0.0 if t == f else np.inf)


def calibrated_coverage(
    cases: list[dict],
    validation: Callable[[dict], bool] | None = None,
    *,
    calibration_cases: Sequence[dict] = (),
) -> dict:
    """Per-effect interval factors chosen on the validation cases (default: even case numbers)
    and on `calibration_cases` (another run: all of them): the 90th percentile of the widening
    each value needed, at least 1; effects with fewer than 5 values take the pooled factor. The
    coverage they give on the other (held-out) cases of `cases`."""
    validation = validation or (lambda c: c["case"] % 2 == 0)
    chosen_on = [c for c in cases if validation(c)] + list(calibration_cases)
    val = [(r["effect"], _needed_factor(r, c)) for c in chosen_on for r in c.get("coverage", [])]
    held = [c for c in cases if not validation(c)]
    pooled = max(1.0, float(np.quantile([f for _, f in val], 0.9))) if val else 1.0
    factors = {}
    for e in EFFECTS:
        need = [f for name, f in val if name == e]
        factors[e] = max(1.0, float(np.quantile(need, 0.9))) if len(need) >= 5 else pooled
    per, hits = {}, []
    for case, r in ((c, r) for c in held for r in c.get("coverage", [])):
        ok = _needed_factor(r, case) <= factors[r["effect"]]
        hits.append(ok)
        per.setdefault(r["effect"], []).append(ok)
    return {
        "factors": factors,
        "validation_values": len(val),
        "held_out_cases": sum(bool(c.get("coverage")) for c in held),
        "held_out_values": len(hits),
        "held_out_rate": float(np.mean(hits)) if hits else None,
        "held_out_per_effect": {e: {"values": len(v), "rate": float(np.mean(v))} for e, v in per.items()},
    }


def spurious_table(cases: list[dict], effects: Sequence[str] = EFFECTS) -> dict:
    """False naming on the hard set: share of null and of non-null cases with a spurious
    effect, and per library effect how often it is named in the cases that lack it."""
    nulls = [c for c in cases if not c["injected"]]
    rest = [c for c in cases if c["injected"]]
    rate = lambda cs: sum(bool(c["false"]) for c in cs) / len(cs) if cs else 0.0  # noqa: E731
    per = {}
    for e in effects:
        lacking = [c for c in cases if e not in c["injected"]]
        per[e] = {"cases_lacking": len(lacking), "named_falsely": sum(e in c["false"] for c in lacking)}
    return {
        "cases": len(cases),
        "null_cases": len(nulls),
        "null_with_false_effect": rate(nulls),
        "non_null_cases": len(rest),
        "non_null_with_false_effect": rate(rest),
        "all_with_false_effect": rate(cases),
        "per_effect": per,
        "cases_reported_ambiguous": sum(bool(c.get("ambiguous")) for c in cases),
        "false_not_flagged": sum(bool(c["false"]) and not truth_offered(c) for c in cases),
    }


def truth_offered(case: dict) -> bool:
    """Is the injected set among the sets the ambiguity report offers as explaining the logs as
    well as the named one (a false name the report flags, not a confident one)?"""
    return any(set(alt) == set(case["injected"]) for alt in case.get("ambiguous", []))


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
        "interval_coverage": coverage_table(cases),
        "interval_coverage_calibrated": calibrated_coverage(cases),
        "false_naming": spurious_table(cases),
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
