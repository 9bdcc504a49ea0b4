"""`safesysid sweep`: randomized closed-loop trials on a local process pool (README.md, "Commands").

Each trial is a random scene drawn from its own seed (app/sweeps.py: start, obstacles, payload
0-8 lb) and, unless --nominal, made adversarial: one box 1-5 cm from the arm at the start, torque
noise at the declared bound and the real arm's parameters drawn inside their box. Summaries
stream to DIR/trials.jsonl, one line per finished trial, so an interrupted sweep resumes where it
stopped; aggregate.json and report.md count every failure with the seeds that reproduce it
(`safesysid run` on the scene).
"""

from __future__ import annotations

import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
from safesysid.cli import BadInput

LIMIT_KEYS = ("max_commanded_torque_ratio", "max_joint_limit_ratio", "max_velocity_ratio")
PARAMETERS = ("m", "mcx", "mcy", "mcz", "Ixx", "Iyy", "Izz", "Ixy", "Iyz", "Ixz")


def make_adversarial(scene):
    """Noise at the declared bound, robot parameters drawn inside their box."""
    scene.noise.torque_ratio = scene.noise.declared_torque_ratio
    scene.noise.torque_floor_Nm = scene.noise.declared_torque_floor_Nm
    scene.noise.distribution = "uniform"
    scene.plant.robot_parameters = "drawn"
    return scene


NEAR_CLEARANCE_M = (0.01, 0.05)  # adversarial: the first box starts 1-5 cm outside the planner's spheres


def trial_scene(base, seed, adversarial=True):
    """The scene of one trial: a pure function of the base scenario and the seed."""
    from safesysid.sweeps import random_scene

    near = NEAR_CLEARANCE_M if adversarial else None
    scene = random_scene(base, np.random.default_rng(seed), seed=seed, near_clearance_m=near)
    return make_adversarial(scene) if adversarial else scene


def run_trial(scenario_path, seed, method, adversarial=True, scenario_text=()):
    """One closed-loop trial (a worker process): its summary, with the seed that replays it."""
    from safesysid.online import run_online
    from safesysid.scenario import load_scenario

    scene = trial_scene(load_scenario(scenario_path, overrides=list(scenario_text)), seed, adversarial)
    summary = run_online(scene, None, method=method, seed=seed, write=False)
    summary["trial_seed"] = seed
    summary["obstacles"] = [{"xyz_m": o.xyz_m, "rpy_rad": o.rpy_rad, "size_m": o.size_m} for o in scene.obstacles]
    summary["q0_rad"] = list(scene.q0_rad)
    return summary


def _read_done(path):
    done = []
    if path.exists():
        for line in path.read_text().splitlines():
            if line.strip():
                try:
                    done.append(json.loads(line))
                except json.JSONDecodeError:  # a line cut by a crash: run that trial again
                    continue
    return done


def _limit_violated(s):
    return max(s[k] for k in LIMIT_KEYS) > 1.0 + 1e-9


def aggregate(trials):
    """aggregate.json from the trial summaries (its keys are a stable interface: add, never rename)."""

    def seeds(pred):
        return sorted(int(s["trial_seed"]) for s in trials if pred(s))

    failures = {}
    for s in trials:
        if s.get("failure"):
            failures.setdefault(s["failure"], []).append(int(s["trial_seed"]))
    widths = (
        np.array([np.subtract(s["estimate"]["upper"], s["estimate"]["lower"]) for s in trials])
        if trials
        else np.zeros((0, 10))
    )
    return {
        "trials": len(trials),
        "collisions": len(seeds(lambda s: s["collisions"] > 0)),
        "limit_violations": len(seeds(_limit_violated)),
        "tracking_bound_violations": len(seeds(lambda s: s["max_tracking_error_ratio"] > 1.0 + 1e-9)),
        "containment_rate": float(np.mean([s["contains_truth"] for s in trials])) if trials else float("nan"),
        "inconsistent_estimates": len(seeds(lambda s: s["estimate"].get("consistent") is False)),
        "deadline_misses": int(sum(s["planner"]["missed_deadlines"] for s in trials)),
        "brakes": int(sum(s["planner"]["brakes"] for s in trials)),
        "failures_by_reason": {k: sorted(v) for k, v in failures.items()},
        "seeds": {
            "collision": seeds(lambda s: s["collisions"] > 0),
            "limit_violation": seeds(_limit_violated),
            "tracking_violation": seeds(lambda s: s["max_tracking_error_ratio"] > 1.0 + 1e-9),
            "truth_outside": seeds(lambda s: not s["contains_truth"]),
        },
        "min_clearance_m": min((s["min_clearance_m"] for s in trials), default=float("nan")),
        **{k: max((s[k] for s in trials), default=float("nan")) for k in LIMIT_KEYS},
        "max_tracking_error_ratio": max((s["max_tracking_error_ratio"] for s in trials), default=float("nan")),
        "width_per_parameter": {
            name: {"median": float(np.median(widths[:, k])), "p90": float(np.percentile(widths[:, k], 90))}
            for k, name in enumerate(PARAMETERS)
        }
        if len(widths)
        else {},
    }


def report_markdown(agg, scenario, methods, wall_s):
    lines = [
        f"# Sweep: {scenario}, methods {', '.join(methods)}",
        "",
        f"{agg['trials']} trials in {wall_s:.0f} s ({60 * agg['trials'] / max(wall_s, 1e-9):.1f} trials/min).",
        "",
        "| check | count | worst |",
        "|---|---|---|",
        f"| collisions (independent geometry) | {agg['collisions']} | min clearance {agg['min_clearance_m']:.3f} m |",
        f"| limit violations (commanded torque before saturation, joints, velocities) | {agg['limit_violations']} | "
        f"torque {agg['max_commanded_torque_ratio']:.2f}, joint {agg['max_joint_limit_ratio']:.2f}, "
        f"velocity {agg['max_velocity_ratio']:.2f} of the limit |",
        f"| tracking-tube violations | {agg['tracking_bound_violations']} "
        f"| {agg['max_tracking_error_ratio']:.2f} of the bound |",
        f"| truth outside the final interval | {len(agg['seeds']['truth_outside'])} "
        f"| containment {agg['containment_rate']:.3f} |",
        f"| inconsistent estimates | {agg['inconsistent_estimates']} | |",
        f"| planner deadline misses / brakes | {agg['deadline_misses']} / {agg['brakes']} | |",
        "",
    ]
    if agg["failures_by_reason"]:
        lines += ["Failures by reason (trial seeds):", ""]
        lines += [f"- {k}: {v}" for k, v in agg["failures_by_reason"].items()]
        lines.append("")
    if agg["width_per_parameter"]:
        lines += ["| parameter | median width | p90 width |", "|---|---|---|"]
        lines += [f"| {k} | {v['median']:.4g} | {v['p90']:.4g} |" for k, v in agg["width_per_parameter"].items()]
    return "\n".join(lines) + "\n"


def cmd_sweep(args):
    from safesysid.scenario import METHODS, load_scenario

    path = Path(args.scenario)
    scenario = load_scenario(
        path, overrides=args.scenario_text
    )  # validates (exit 2 on bad input) before any worker starts
    methods = [m.strip() for m in (args.methods or scenario.method).split(",") if m.strip()]
    for m in methods:
        if m not in METHODS:
            raise BadInput(f"--methods: {m!r} is not one of {', '.join(METHODS)}")
    if args.trials < 1:
        raise BadInput("--trials: must be >= 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jsonl = out / "trials.jsonl"
    done = _read_done(jsonl)
    have = {(s["method"], int(s["trial_seed"])) for s in done}
    todo = [(m, args.seed + k) for k in range(args.trials) for m in methods if (m, args.seed + k) not in have]
    print(
        f"sweep: {len(have)} trials already in {jsonl}, {len(todo)} to run on {args.workers} worker(s)", file=sys.stderr
    )
    wall0 = time.perf_counter()
    with jsonl.open("a") as fh, ProcessPoolExecutor(max_workers=args.workers) as pool:
        futures = {
            pool.submit(run_trial, str(path), seed, m, not args.nominal, args.scenario_text): (m, seed)
            for m, seed in todo
        }
        for k, fut in enumerate(as_completed(futures), 1):
            summary = fut.result()
            fh.write(json.dumps(summary, default=float) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
            done.append(summary)
            m, seed = futures[fut]
            print(
                f"[{k}/{len(todo)}] {m} seed {seed}: {'ok' if summary['success'] else summary['failure']}",
                file=sys.stderr,
            )
    wall = time.perf_counter() - wall0
    agg = aggregate(
        [s for s in done if s["method"] in methods and args.seed <= s["trial_seed"] < args.seed + args.trials]
    )
    agg["wall_time_s"] = wall
    (out / "aggregate.json").write_text(json.dumps(agg, indent=2, default=float))
    text = report_markdown(agg, scenario.name, methods, wall)
    (out / "report.md").write_text(text)
    print(text)
    return 0 if agg["collisions"] == agg["limit_violations"] == agg["tracking_bound_violations"] == 0 else 1
