"""`safesysid run` (README.md, "Commands"); `safesysid compare` is in compare_cli.py."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from safesysid.cli import BadInput
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.systems.config import METHODS, Scenario


def scenario_path(args: argparse.Namespace) -> Path:
    return Path(args.scenario) if args.scenario else SCENARIOS_DIR / "quickstart.yaml"


def _scenario(args):
    from safesysid.setup_check import check_setup

    scenario = load_scenario(scenario_path(args), overrides=args.scenario_text)
    check_setup(scenario)
    return scenario


def _method(name, scenario):
    method = name or scenario.method
    if method not in METHODS:
        raise BadInput(f"--method: {method!r} is not one of {', '.join(METHODS)}")
    return method


def method_list(text: str) -> list[str]:
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


def identified_body(scenario: Scenario, summary: dict) -> str:
    """The summary's truth mass explained: last link + gripper + the dumbbell (from the scenario's file)."""
    from safesysid.report import identified_body_text
    from safesysid.systems.model.loading import resolve_path, scenario_dir
    from safesysid.systems.model.payload import load_dumbbells

    name = summary["payload_true"].get("dumbbell")
    mass = None
    if name:
        dumbbells = load_dumbbells(resolve_path(scenario.payload.dumbbells_file, scenario_dir(scenario)))
        mass = dumbbells[name].mass_kg if name in dumbbells else None
    return identified_body_text(summary["payload_true"]["theta"][0], name, mass)


def _mark_interrupted(out: Path, summary: dict) -> dict:
    """A run stopped by Ctrl-C did not succeed: say so in its summary.json."""
    summary.update(interrupted=True, success=False, failure=summary["failure"] or "interrupted")
    log = out / "log.csv"
    if log.exists():  # the simulated time reached (sim_time_s is the time the run was meant to last)
        summary["interrupted_at_s"] = float(log.read_text().rstrip().rsplit("\n", 1)[-1].split(",", 1)[0])
    path = out / "summary.json"
    if path.exists():
        path.write_text(json.dumps(summary, indent=2, default=float))
    return summary


def run_exit_status(summary: dict) -> int:
    """0 when the run succeeded (and the truth, where known, is inside the interval), else 1."""
    return 0 if summary["success"] and summary.get("contains_truth") is not False else 1


def cmd_run(args: argparse.Namespace) -> int:
    from safesysid.online import run_online
    from safesysid.progress import RunDisplay, interruptible, serve_until_interrupt

    scenario = _scenario(args)
    method = _method(args.method, scenario)
    if getattr(args, "arm", None) == "lcm" or scenario.arm.driver == "lcm":
        from safesysid.online_lcm import cmd_run_lcm

        return cmd_run_lcm(args, scenario, method)
    if args.realtime_rate < 0:
        raise BadInput("--realtime-rate: must be >= 0")
    display = RunDisplay(
        meshcat=args.meshcat or args.wait_for_viewer,
        wait_for_viewer=args.wait_for_viewer,
        realtime_rate=args.realtime_rate,
        keep_serving=not args.no_serve,
    )
    with interruptible(display):
        summary = run_online(scenario, args.out, method=method, seed=args.seed, live_meshcat=display)
    out = Path(args.out)
    if display.interrupted:
        summary = _mark_interrupted(out, summary)
    print(_headline(summary))
    print(f"  ({identified_body(scenario, summary)})")
    print(f"wrote {out / 'summary.json'}, log.csv, plots, replay.html", file=sys.stderr)
    serve_until_interrupt(display)
    return 130 if display.interrupted else run_exit_status(summary)
