"""Closed-loop gap diagnosis: the online loop's own logs as the diagnosis' input, and its
corrected model as the loop's model again (docs/diagnosis.md, "Closed loop").

For each hidden plant effect (a `plant.effects` field the models above the plant do not know)
and seed, one case:
  1. run the online loop (run_online, what `safesysid run` calls) on the plant with the effect;
  2. diagnose its log.csv (run_diagnosis, what `safesysid diagnose` calls): fit on the first two
     thirds, the last third held out and scored once; the starting model is the run's robot
     model with the dumbbell's inertia on the end effector (a lab knows the weight it grasped;
     without it the payload is most of the gap and soaks up an offset);
  3. when the correction has a term the models above the plant use (friction, armature, offset,
     the torque signal's time law), rerun the loop with `robot.corrected_model` on the same
     hidden-effect plant and seed: controller, planner and estimator get the correction, the
     simulated arm keeps the true effect. Otherwise the rerun would be the same run.
Each case writes OUT/EFFECT_sSEED/case.json; `table` prints both tables from the cases there.

    python experiments/closed_loop_diagnosis.py matrix --out DIR [--effects E ...] [--seeds 0 1 2]
    python experiments/closed_loop_diagnosis.py case EFFECT SEED --out DIR [--scenario-text YAML]
    python experiments/closed_loop_diagnosis.py table DIR
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

SCENARIO = "quickstart.yaml"
CHECK_FRACTION = 1 / 3  # the last third of each run's log is held out
LOOP_SIDE = {"coulomb_friction", "viscous_friction", "armature", "torque_offset", "time_delay"}
SEEDS = (0, 1, 2)


@dataclasses.dataclass(frozen=True)
class Injected:
    """A hidden plant effect and what the diagnosis should report for it."""

    fields: dict  # plant.effects override
    effect: str  # the diagnosis' name
    keys: tuple  # params keys compared (diagnosis.json units)
    expected: tuple  # the values those keys should take, on `joints` for per-joint keys
    joints: tuple = ()  # 0-based joints the effect is on (per-joint effects)
    time_law: str = ""  # time_delay: shift | lag


RIGID = 1.0e6  # N m/rad: a joint the stiffness case leaves stiff
# The softened joints: stiffer than the controller's position gain, which the quasi-static
# encoders' one-step-late offset needs (systems/plant/station.py; 300 N m/rad oscillates).
SOFT = 3000.0
INJECTED = {
    "torque_sensor_offset": Injected(
        {"torque_sensor_offset_Nm": [0, 1.5, 0, 1.0, 0, 0, 0]}, "torque_offset", ("offset_Nm",), (1.5, 1.0), (1, 3)
    ),
    "torque_sensor_lag": Injected({"torque_sensor_lag_s": 0.03}, "time_delay", ("delay_s",), (0.03,), time_law="lag"),
    "torque_sensor_delay": Injected(
        {"torque_sensor_delay_s": 0.02}, "time_delay", ("delay_s",), (0.02,), time_law="shift"
    ),
    "time_delay": Injected({"time_delay_s": 0.02}, "time_delay", ("delay_s",), (-0.02,), time_law="shift"),
    "torque_sensor_scale": Injected(
        {"torque_sensor_scale": [1, 0.9, 1, 0.9, 1, 1, 1]}, "torque_scale", ("scale",), (0.9, 0.9), (1, 3)
    ),
    "load_friction": Injected(
        {"load_friction_mu": [0, 0.08, 0, 0.06, 0, 0, 0]}, "load_friction", ("mu",), (0.08, 0.06), (1, 3)
    ),
    "stribeck_friction": Injected(
        {"stribeck_friction_Nm": [0, 1.5, 0, 1.0, 0, 0, 0], "stribeck_velocity_rad_s": 0.05},
        "stribeck_friction",
        ("Fs_Nm",),
        (1.5, 1.0),
        (1, 3),
    ),
    "base_tilt": Injected({"base_tilt_rad": [0.03, -0.02]}, "base_tilt", ("roll_rad", "pitch_rad"), (0.03, -0.02)),
    "joint_stiffness": Injected(
        {"joint_stiffness_Nm_rad": [RIGID, SOFT, RIGID, SOFT, RIGID, RIGID, RIGID]},
        "joint_elasticity",
        ("compliance_rad_per_Nm",),
        (1 / SOFT, 1 / SOFT),
        (1, 3),
    ),
    "none": Injected({}, "", (), ()),  # the null case: nothing hidden, nothing should be named
}


def split_log(log: Path, fit: Path, check: Path) -> float:
    """Write the first (1 - CHECK_FRACTION) of a log.csv to `fit` and the rest to `check`; the split time."""
    with open(log, newline="") as f:
        rows = list(csv.reader(f))
    t = np.array([float(r[0]) for r in rows[1:]])
    split = float(t[0] + (1 - CHECK_FRACTION) * (t[-1] - t[0]))
    for path, keep in ((fit, t < split), (check, t >= split)):
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(rows[0])
            w.writerows(r for r, k in zip(rows[1:], keep) if k)
    return split


def loop_metrics(summary: dict, log: Path) -> dict:
    """What the loop shows of a model error: tracking, robust input, intervals, consistency."""
    with open(log, newline="") as f:
        rows = list(csv.DictReader(f))
    n = sum(1 for k in rows[0] if k.startswith("qd"))
    err = np.array([[float(r[f"qd{j}"]) - float(r[f"q{j}"]) for j in range(1, n + 1)] for r in rows])
    est = summary["estimate"]
    widths = (np.array(est["upper"]) - np.array(est["lower"])).tolist()
    robust = (summary.get("robust_input") or {}).get("identification") or {}
    first_bad = [e["t"] for e in summary["events"] if e["kind"] == "inconsistent_estimate"]
    return {
        "success": summary["success"],
        "failure": summary["failure"],
        "max_tracking_error_rad": summary["max_tracking_error_rad"],
        "rms_tracking_error_rad": float(np.sqrt(np.mean(err**2))),
        "robust_active_fraction": robust.get("active_fraction"),
        "robust_max_lambda_Nm": robust.get("max_lambda_Nm"),
        "interval_widths": widths,
        "mass_width_kg": widths[0],
        "consistent": est["consistent"],
        "first_inconsistent_t_s": first_bad[0] if first_bad else None,
        "contains_truth": summary["contains_truth"],
        "updates": summary["sysid"]["updates"],
    }


def naming(result: dict, injected: Injected) -> dict:
    """Effects named (significant) against the injected one: exact / spurious / missed, and the
    injected value's error (and whether its statistical interval holds it)."""
    named = list(result["cause"])
    entry = next((e for e in result["effects"] if e["name"] == injected.effect), None)
    found = not injected.effect or injected.effect in named  # the null case has nothing to find
    if found and injected.time_law:
        found = entry["params"].get("time_law") == injected.time_law
    spurious = [e for e in named if e != injected.effect]
    out = {"named": named, "found": found, "spurious": spurious, "exact": found and not spurious}
    out["law"] = entry["params"].get("time_law") if entry and injected.time_law else None
    if entry is None or not found:
        return out | {"value": None, "value_error": None, "relative_error": None, "in_interval": None}
    value, lo, hi = _pick(entry["params"], injected), None, None
    intervals = entry.get("intervals") or {}
    if all(intervals.get(k) is not None for k in injected.keys):
        pairs = [_pick_interval(intervals[k], injected) for k in injected.keys]
        lo, hi = np.concatenate([p[0] for p in pairs]), np.concatenate([p[1] for p in pairs])
    expected = np.array(injected.expected, float)
    error = value - expected
    out |= {
        "value": value.tolist(),
        "expected": expected.tolist(),
        "value_error": float(np.max(np.abs(error))),
        "relative_error": float(np.max(np.abs(error) / np.abs(expected))),
        "in_interval": None if lo is None else bool(np.all((lo <= expected) & (expected <= hi))),
    }
    return out


def _pick(params: dict, injected: Injected) -> np.ndarray:
    parts = [np.atleast_1d(np.asarray(params[k], float)) for k in injected.keys]
    return np.concatenate([p[list(injected.joints)] if injected.joints else p for p in parts])


def _pick_interval(pair, injected: Injected) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = (np.atleast_1d(np.array(x, dtype=float)) for x in pair)  # None (no information) -> nan
    if injected.joints:
        lo, hi = lo[list(injected.joints)], hi[list(injected.joints)]
    return np.where(np.isnan(lo), -np.inf, lo), np.where(np.isnan(hi), np.inf, hi)


def loop_corrected_model(corrected: Path, out: Path) -> tuple[Path, list[str]]:
    """The corrected model the loop can run: without a diagnosed payload (the scenario's dumbbell is
    the payload; robot.corrected_model refuses one). Returns the file and the effects it dropped."""
    doc = yaml.safe_load(corrected.read_text())
    dropped = [e["name"] for e in doc["effects"] if e["name"] == "payload"]
    if not dropped:
        return corrected, []
    doc["effects"] = [e for e in doc["effects"] if e["name"] != "payload"]
    out.write_text(yaml.safe_dump(doc, sort_keys=False))
    return out, dropped


def run_case(effect: str, seed: int, out: str | Path, *, overrides: list | tuple = ()) -> dict:
    """One case (module docstring); writes OUT/EFFECT_sSEED/case.json and returns it."""
    from safesysid.diagnose_cli import run_diagnosis
    from safesysid.online import run_online
    from safesysid.scenario import SCENARIOS_DIR, load_scenario, robot_from_scenario

    injected, base = INJECTED[effect], SCENARIOS_DIR / SCENARIO
    folder = Path(out) / f"{effect}_s{seed}"
    true_scenario = load_scenario(base, overrides=[*overrides, {"plant": {"effects": injected.fields}}])
    summary = run_online(true_scenario, folder / "run", seed=seed)
    fit, check = folder / "fit.csv", folder / "check.csv"
    split = split_log(folder / "run" / "log.csv", fit, check)
    robot = robot_from_scenario(load_scenario(base, overrides=list(overrides)))
    model = robot.with_end_effector_theta(summary["payload_true"]["theta"])
    d = run_diagnosis(model, [fit], [check], out=folder / "diagnosis", model_path=base, plots=False)
    corrected, dropped = loop_corrected_model(
        folder / "diagnosis" / "corrected_model.yaml", folder / "corrected_model_loop.yaml"
    )
    loop_terms = [e["name"] for e in yaml.safe_load(corrected.read_text())["effects"] if e["name"] in LOOP_SIDE]
    rerun = None
    if loop_terms:
        corrected_scenario = load_scenario(base, overrides=[*overrides, {"robot": {"corrected_model": str(corrected)}}])
        rerun_summary = run_online(corrected_scenario, folder / "rerun", seed=seed, true_scenario=true_scenario)
        rerun = loop_metrics(rerun_summary, folder / "rerun" / "log.csv")
    test = d.result["test"]
    case = {
        "effect": effect,
        "seed": seed,
        "scenario": SCENARIO,
        "overrides": list(overrides),
        "hidden_effects": injected.fields,
        "check_from_s": split,
        "diagnosis": naming(d.result, injected)
        | {
            "held_out_rms_before_Nm": test["rms_before"],
            "held_out_rms_after_Nm": test["rms_after"],
            "held_out_reduction": test["reduction"],
            "ambiguous": [[s["effects"] for s in a["sets"]] for a in d.result["ambiguous"]],
        },
        "dropped_for_the_loop": dropped,
        "loop_terms": loop_terms,
        "uncorrected": loop_metrics(summary, folder / "run" / "log.csv"),
        "corrected": rerun,
    }
    (folder / "case.json").write_text(json.dumps(case, indent=2, default=float))
    return case


def run_matrix(out: Path, effects, seeds, overrides) -> None:
    """Every case not yet done, one process each (the Drake runs' memory is freed between cases)."""
    for effect in effects:
        for seed in seeds:
            folder = out / f"{effect}_s{seed}"
            if (folder / "case.json").is_file():
                continue
            folder.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, __file__, "case", effect, str(seed), "--out", str(out)]
            cmd += [x for o in overrides for x in ("--scenario-text", o)]
            with open(folder / "case.log", "w") as log:
                code = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT)
            print(f"{effect} seed {seed}: {'done' if code == 0 else f'failed ({code}), see case.log'}", flush=True)


def load_cases(out: Path) -> dict[str, list[dict]]:
    """case.json files by effect (in INJECTED's order), each list by seed."""
    cases = [json.loads(p.read_text()) for p in sorted(Path(out).glob("*/case.json"))]
    by_effect = {e: sorted((c for c in cases if c["effect"] == e), key=lambda c: c["seed"]) for e in INJECTED}
    return {e: cs for e, cs in by_effect.items() if cs}


def _each(values, fmt) -> str:
    return " / ".join("–" if v is None else fmt(v) for v in values)


def _tally(per_case: list[set]) -> str:
    """'name ×cases' for every name in any case's set."""
    names = sorted(set().union(*per_case))
    return ", ".join(f"{n} ×{sum(n in found for found in per_case)}" for n in names) or "none"


def diagnosis_table(by_effect: dict[str, list[dict]]) -> list[str]:
    """Effect injected -> named (exact / spurious / missed), value error, held-out reduction."""
    lines = [
        "| effect injected (seeds) | diagnosis' name | exact | spurious | missed | value error (relative) "
        "| in 90 % interval | held-out reduction | reported ambiguous with |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for effect, cases in by_effect.items():
        diags = [c["diagnosis"] for c in cases]
        counts = _tally([set(d["spurious"]) for d in diags])
        ambiguous = _tally([{e for sets in d["ambiguous"] for s in sets for e in s} - set(d["named"]) for d in diags])
        law = INJECTED[effect].time_law
        lines.append(
            f"| {effect} ({', '.join(str(c['seed']) for c in cases)}) "
            f"| {INJECTED[effect].effect or '(nothing)'}{f' ({law})' if law else ''} "
            f"| {sum(d['exact'] for d in diags)}/{len(diags)} | {counts} "
            f"| {sum(not d['found'] for d in diags)}/{len(diags)} "
            f"| {_each([d['relative_error'] for d in diags], lambda v: f'{100 * v:.0f} %')} "
            f"| {_each([d['in_interval'] for d in diags], lambda v: 'yes' if v else 'no')} "
            f"| {_each([d['held_out_reduction'] for d in diags], lambda v: f'{100 * v:.1f} %')} | {ambiguous} |"
        )
    return lines


def loop_table(by_effect: dict[str, list[dict]]) -> list[str]:
    """Uncorrected -> corrected rerun on the same hidden-effect plant and seed. A seed whose
    correction has no term above the plant was not rerun: its corrected run is the run itself."""
    lines = [
        "| effect injected (seeds) | correction the loop uses (seeds) | RMS tracking error [mrad] "
        "| robust input active | mass interval width [kg] | inconsistent runs | interval holds the truth |",
        "|---|---|---|---|---|---|---|",
    ]
    for effect, cases in by_effect.items():
        unc = [c["uncorrected"] for c in cases]
        cor = [c["corrected"] or c["uncorrected"] for c in cases]
        rerun = any(c["corrected"] for c in cases)

        def pair(key, fmt, unc=unc, cor=cor, rerun=rerun):
            before = _each([m[key] for m in unc], fmt)
            return f"{before} → {_each([m[key] for m in cor], fmt)}" if rerun else before

        def count(key, want, unc=unc, cor=cor, rerun=rerun):
            before = f"{sum(m[key] == want for m in unc)}/{len(unc)}"
            return f"{before} → {sum(m[key] == want for m in cor)}/{len(cor)}" if rerun else before

        groups: dict[str, list[str]] = {}
        for c in cases:
            groups.setdefault(", ".join(c["loop_terms"]) or "none", []).append(str(c["seed"]))
        terms = "; ".join(f"{t} ({', '.join(seeds)})" for t, seeds in groups.items())
        lines.append(
            f"| {effect} ({', '.join(str(c['seed']) for c in cases)}) | {terms} "
            f"| {pair('rms_tracking_error_rad', lambda v: f'{1e3 * v:.2f}')} "
            f"| {pair('robust_active_fraction', lambda v: f'{100 * v:.0f} %')} "
            f"| {pair('mass_width_kg', lambda v: f'{v:.3f}')} | {count('consistent', False)} "
            f"| {count('contains_truth', True)} |"
        )
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="verb", required=True)
    m = sub.add_parser("matrix", help="every case not yet done, one process each")
    m.add_argument("--out", required=True, type=Path)
    m.add_argument("--effects", nargs="+", default=list(INJECTED), choices=list(INJECTED))
    m.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    c = sub.add_parser("case", help="one effect and seed")
    c.add_argument("effect", choices=list(INJECTED))
    c.add_argument("seed", type=int)
    c.add_argument("--out", required=True, type=Path)
    for q in (m, c):
        q.add_argument("--scenario-text", action="append", default=[], help="YAML layered over the scenario")
    t = sub.add_parser("table", help="print both tables from the case.json files in DIR")
    t.add_argument("out", type=Path)
    args = p.parse_args(argv)
    if args.verb == "matrix":
        run_matrix(args.out, args.effects, args.seeds, args.scenario_text)
    elif args.verb == "case":
        run_case(args.effect, args.seed, args.out, overrides=args.scenario_text)
    else:
        by_effect = load_cases(args.out)
        print("\n".join(diagnosis_table(by_effect) + [""] + loop_table(by_effect)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
