"""`safesysid run` and `safesysid compare` (README.md, "Commands")."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

from safesysid.cli import BadInput
from safesysid.scenario import METHODS, SCENARIOS_DIR, load_scenario

SUMMARY_COLUMNS = [
    "method",
    "trial",
    "seed",
    "success",
    "failure",
    "collisions",
    "min_clearance_m",
    "max_torque_ratio",
    "max_tracking_error_rad",
    "tracking_bound_rad",
    "contains_truth",
    "cond_Y",
    "mass_estimate_kg",
    "mass_width_kg",
    "brakes",
    "median_solve_s",
    "wall_time_s",
]


def _scenario(args):
    path = Path(args.scenario) if args.scenario else SCENARIOS_DIR / "quickstart.yaml"
    return load_scenario(path, overrides=args.scenario_text)


def _method(name, scenario):
    method = name or scenario.method
    if method not in METHODS:
        raise BadInput(f"--method: {method!r} is not one of {', '.join(METHODS)}")
    return method


def method_list(text):
    """--methods: comma-separated names, or "all" (every method of the paper's table, in its order)."""
    names = [m.strip() for m in text.split(",") if m.strip()]
    return list(METHODS) if names == ["all"] else names


def _headline(s):
    est = s["estimate"]
    mass, lo, hi = est["nominal"][0], est["lower"][0], est["upper"][0]
    outcome = "success" if s["success"] else f"FAILED: {s['failure']}"
    return (
        f"{s['scenario']} / {s['method']} (seed {s['seed']}): {outcome}; "
        f"collisions {s['collisions']}, min clearance {s['min_clearance_m']:.3f} m, "
        f"max |u|/limit {s['max_torque_ratio']:.2f}, "
        f"tracking {s['max_tracking_error_rad']:.4f}/{s['tracking_bound_rad']:.4f} rad; "
        f"mass {mass:.3f} kg in [{lo:.3f}, {hi:.3f}] (true {s['payload_true']['theta'][0]:.3f}), "
        f"contains truth: {s['contains_truth']}, cond(Y) {s['cond_Y']:.1f}"
    )


def cmd_run(args):
    from safesysid.online import run_online

    scenario = _scenario(args)
    method = _method(args.method, scenario)
    summary = run_online(scenario, args.out, method=method, seed=args.seed, live_meshcat=args.meshcat)
    print(_headline(summary))
    print(f"wrote {Path(args.out) / 'summary.json'}, log.csv, plots, replay.html", file=sys.stderr)
    return 0


def row_of(summary, trial):
    est = summary["estimate"]
    times = sorted(summary["planner"]["solve_time_s"])
    return {
        "method": summary["method"],
        "trial": trial,
        "seed": summary["seed"],
        "success": summary["success"],
        "failure": summary["failure"] or "",
        "collisions": summary["collisions"],
        "min_clearance_m": summary["min_clearance_m"],
        "max_torque_ratio": summary["max_torque_ratio"],
        "max_tracking_error_rad": summary["max_tracking_error_rad"],
        "tracking_bound_rad": summary["tracking_bound_rad"],
        "contains_truth": summary["contains_truth"],
        "cond_Y": summary["cond_Y"],
        "mass_estimate_kg": est["nominal"][0],
        "mass_width_kg": est["upper"][0] - est["lower"][0],
        "brakes": summary["planner"]["brakes"],
        "median_solve_s": times[len(times) // 2] if times else float("nan"),
        "wall_time_s": summary["wall_time_s"],
    }


def cmd_compare(args):
    from safesysid.online import run_online
    from safesysid.report import markdown_table

    scenario = _scenario(args)
    methods = method_list(args.methods)
    for m in methods:
        _method(m, scenario)
    if args.trials < 1:
        raise BadInput("--trials: must be >= 1")
    out = Path(args.out)
    rows = []
    for trial in range(args.trials):
        for method in methods:
            seed = scenario.seed + trial
            summary = run_online(scenario, out / f"{method}_{trial}", method=method, seed=seed)
            rows.append(row_of(summary, trial))
            print(_headline(summary), flush=True)
    out.mkdir(parents=True, exist_ok=True)
    with (out / "table.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=SUMMARY_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    (out / "table.md").write_text(
        f"# {scenario.name}: {', '.join(methods)}, {args.trials} trial(s)\n\n" + markdown_table(rows, SUMMARY_COLUMNS)
    )
    (out / "table.json").write_text(json.dumps(rows, indent=2, default=float))
    print(markdown_table(rows, SUMMARY_COLUMNS))
    return 0
