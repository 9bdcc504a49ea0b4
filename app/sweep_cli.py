"""`safesysid sweep`: randomized closed-loop trials on a local process pool or Ray (README.md, "Sweeps").

Each trial is a random scene drawn from its own seed (app/sweeps.py: start, obstacles, payload
0-8 lb) and, unless --nominal, made adversarial: one box 1-5 cm from the arm at the start, torque
noise at the declared bound and the real arm's parameters drawn inside their box. Summaries
stream to DIR/trials.jsonl, one line per finished trial, so an interrupted sweep resumes where it
stopped (SIGINT and SIGTERM stop the workers; finished trials are on disk); aggregate.json and
report.md count every failure with the seeds that reproduce it and the `safesysid run` line that
replays the trial. The planner's budget is the scenario's (default: iterations), so a trial's
result does not depend on the machine's load, the executor or the number of workers.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
import traceback
from collections.abc import Generator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml
from safesysid import pool
from safesysid.cli import BadInput, require_positive
from safesysid.pool import read_jsonl

if TYPE_CHECKING:
    from safesysid.systems.config import Scenario

LIMIT_KEYS = ("max_commanded_torque_ratio", "max_joint_limit_ratio", "max_velocity_ratio")
PARAMETERS = ("m", "mcx", "mcy", "mcz", "Ixx", "Iyy", "Izz", "Ixy", "Iyz", "Ixz")


def make_adversarial(scene: Scenario) -> Scenario:
    """Noise at the declared bound, robot parameters drawn inside their box."""
    scene.noise.torque_ratio = scene.noise.declared_torque_ratio
    scene.noise.torque_floor_Nm = scene.noise.declared_torque_floor_Nm
    scene.noise.distribution = "uniform"
    scene.plant.robot_parameters = "drawn"
    return scene


NEAR_CLEARANCE_M = (0.01, 0.05)  # adversarial: the first box starts 1-5 cm outside the planner's spheres


def trial_scene(base: Scenario, seed: int, adversarial: bool = True) -> Scenario:
    """The scene of one trial: a pure function of the base scenario and the seed."""
    from safesysid.sweeps import random_scene

    near = NEAR_CLEARANCE_M if adversarial else None
    scene = random_scene(base, np.random.default_rng(seed), seed=seed, near_clearance_m=near)
    return make_adversarial(scene) if adversarial else scene


def replay_text(scene: Scenario) -> str:
    """--scenario-text that turns the base scenario into this trial's scene (`safesysid run` replays
    it): every field trial_scene draws or sets, floats written exactly (repr)."""
    layer = {
        "name": scene.name,
        "seed": int(scene.seed),
        "q0_rad": [float(x) for x in scene.q0_rad],
        "payload": {"dumbbell": scene.payload.dumbbell},
        "obstacles": [
            {"name": o.name, "xyz_m": list(o.xyz_m), "rpy_rad": list(o.rpy_rad), "size_m": list(o.size_m)}
            for o in scene.obstacles
        ],
        "noise": {k: getattr(scene.noise, k) for k in ("torque_ratio", "torque_floor_Nm", "distribution")},
        "plant": {"robot_parameters": scene.plant.robot_parameters},
    }
    return yaml.safe_dump(layer, default_flow_style=True, width=1 << 30, sort_keys=False).strip()


def run_trial(
    scenario_path: str, seed: int, method: str, adversarial: bool = True, scenario_text: Sequence[str] = ()
) -> dict:
    """One closed-loop trial (a pool worker or a Ray task): its summary, with the seed and the
    --scenario-text that replay it. A trial that raises is recorded (failure "error"), not lost."""
    from safesysid.online import run_online
    from safesysid.scenario import load_scenario
    from threadpoolctl import threadpool_limits

    try:
        scene = trial_scene(load_scenario(scenario_path, overrides=list(scenario_text)), seed, adversarial)
        # One BLAS thread: the trials share the cores, and pool, Ray and a replay compute alike.
        with threadpool_limits(1):
            summary = run_online(scene, None, method=method, seed=seed, write=False)
    except Exception as err:  # noqa: BLE001 -- one broken trial must not end a sweep of thousands
        last = traceback.format_exception_only(type(err), err)[-1].strip()
        return {"trial_seed": seed, "method": method, "success": False, "failure": "error", "error": last}
    summary["trial_seed"] = seed
    summary["replay_scenario_text"] = replay_text(scene)
    summary["obstacles"] = [{"xyz_m": o.xyz_m, "rpy_rad": o.rpy_rad, "size_m": o.size_m} for o in scene.obstacles]
    summary["q0_rad"] = list(scene.q0_rad)
    return summary


def replay_command(scenario_path: str | Path, summary: dict, scenario_text: Sequence[str] = ()) -> str:
    """The `safesysid run` command line that reruns one trial."""
    texts = [*scenario_text, summary["replay_scenario_text"]]
    args = ["safesysid", "run", str(scenario_path), "--method", summary["method"], "--seed", str(summary["trial_seed"])]
    args += [x for text in texts for x in ("--scenario-text", text)]
    return shlex.join(args)


def read_trials(path: Path) -> list:
    """The finished trials of DIR/trials.jsonl, one per (method, seed); a line cut by a kill is
    dropped (app/pool.py read_jsonl)."""
    return read_jsonl(path, lambda s: (s["method"], int(s["trial_seed"])))


def _limit_violated(s):
    return max(s[k] for k in LIMIT_KEYS) > 1.0 + 1e-9


def aggregate(trials: list[dict]) -> dict:
    """aggregate.json from the trial summaries (its keys are a stable interface: add, never rename).
    Trials that raised count in `trials` and under failures_by_reason["error"] only."""
    failures = {}
    for s in trials:
        if s.get("failure"):
            failures.setdefault(s["failure"], []).append(int(s["trial_seed"]))
    errors = len(failures.get("error", ()))
    trials, all_trials = [s for s in trials if s.get("failure") != "error"], trials

    def seeds(pred):
        return sorted(int(s["trial_seed"]) for s in trials if pred(s))

    widths = (
        np.array([np.subtract(s["estimate"]["upper"], s["estimate"]["lower"]) for s in trials])
        if trials
        else np.zeros((0, 10))
    )
    return {
        "trials": len(all_trials),
        "errors": errors,
        "collisions": len(seeds(lambda s: s["collisions"] > 0)),
        "limit_violations": len(seeds(_limit_violated)),
        "tracking_bound_violations": len(seeds(lambda s: s["max_tracking_error_ratio"] > 1.0 + 1e-9)),
        "containment_rate": float(np.mean([s["contains_truth"] for s in trials])) if trials else float("nan"),
        "inconsistent_estimates": len(seeds(lambda s: s["estimate"].get("consistent") is False)),
        "deadline_misses": int(sum(s["planner"]["missed_deadlines"] for s in trials)),
        "brakes": int(sum(s["planner"]["brakes"] for s in trials)),
        "failures_by_reason": {k: sorted(v) for k, v in sorted(failures.items())},
        "seeds": {
            "collision": seeds(lambda s: s["collisions"] > 0),
            "limit_violation": seeds(_limit_violated),
            "tracking_violation": seeds(lambda s: s["max_tracking_error_ratio"] > 1.0 + 1e-9),
            "truth_outside": seeds(lambda s: not s["contains_truth"]),
            "inconsistent": seeds(lambda s: s["estimate"].get("consistent") is False),
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


def _flagged(agg):
    """Seeds of every trial the report must let the user replay."""
    return sorted(
        {s for v in agg["failures_by_reason"].values() for s in v} | {s for v in agg["seeds"].values() for s in v}
    )


def report_markdown(agg: dict, scenario: str, methods: Sequence[str], *, replays: Sequence[str] = ()) -> str:
    """report.md: the counts, the widths and a `safesysid run` line per flagged trial."""
    timing = (
        f"{agg['trials_run']} run now in {agg['wall_time_s']:.0f} s on {agg['workers']} {agg['executor']} worker(s): "
        f"{agg['trials_per_minute']:.2f} trials/min"
        if agg["trials_run"]
        else "all already in trials.jsonl"
    )
    lines = [
        f"# Sweep: {scenario}, methods {', '.join(methods)}",
        "",
        f"{agg['trials']} trials ({timing}); planner budget: {agg['planner_budget']}.",
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
        f"| planner deadline misses (wall time) / brakes | {agg['deadline_misses']} / {agg['brakes']} | |",
        f"| trials that raised | {agg['errors']} | |",
    ]
    if agg.get("by_method"):
        lines.append("")
    for method, sub in agg.get("by_method", {}).items():
        lines.append(
            f"- {method}: {sub['trials']} trials, {sub['collisions']} collisions, {sub['limit_violations']} limit "
            f"and {sub['tracking_bound_violations']} tube violations, containment {sub['containment_rate']:.3f}"
        )
    if agg["failures_by_reason"]:
        lines += ["", "Failures by reason (trial seeds):", ""]
        lines += [f"- {k}: {v}" for k, v in agg["failures_by_reason"].items()]
    if agg["width_per_parameter"]:
        lines += ["", "| parameter | median width | p90 width |", "|---|---|---|"]
        lines += [f"| {k} | {v['median']:.4g} | {v['p90']:.4g} |" for k, v in agg["width_per_parameter"].items()]
    if replays:
        lines += ["", "Replay a flagged trial (same scene, same seed, same summary):", "", "```"]
        lines += list(replays)
        lines.append("```")
    return "\n".join(lines) + "\n"


def pool_results(jobs: list[tuple], workers: int) -> Generator[dict, None, None]:
    """Summaries of `jobs` (argument tuples of run_trial) as they finish, on a local process pool."""
    results = pool.pool_results(run_trial, jobs, workers)
    try:
        for _, summary in results:
            yield summary
    finally:
        results.close()  # stops the workers


def ray_results(jobs: list[tuple], address: str, workers: int) -> Generator[dict, None, None]:
    """Summaries of `jobs` as they finish, each trial a Ray task. Uses the Ray instance already
    initialized in this process; otherwise starts a local one (`address` "local", `workers` CPUs)
    or connects to the cluster at `address` ("auto": the one `ray start` made)."""
    try:
        import ray
    except ImportError as err:
        raise BadInput("--ray: the ray package is not installed (pip install 'safesysid[ray]')") from err
    started = not ray.is_initialized()
    if started:
        local = address == "local"
        ray.init(
            address=None if local else address,
            num_cpus=max(1, workers) if local else None,
            include_dashboard=False,
            log_to_driver=False,
        )
    task = ray.remote(num_cpus=1, max_retries=0)(run_trial)
    pending = [task.remote(*job) for job in jobs]
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()


def _methods(text, default):
    from safesysid.systems.config import METHODS

    methods = list(METHODS) if text == "all" else [m.strip() for m in (text or default).split(",") if m.strip()]
    for m in methods:
        if m not in METHODS:
            raise BadInput(f"--methods: {m!r} is not one of {', '.join(METHODS)} (or all)")
    return methods


def cmd_sweep(args: argparse.Namespace) -> int:
    from safesysid.scenario import load_scenario
    from safesysid.setup_check import check_setup

    path = Path(args.scenario)
    texts = list(args.scenario_text)
    scenario = load_scenario(path, overrides=texts)  # validates (exit 2 on bad input) before any worker starts
    check_setup(scenario)
    methods = _methods(args.methods, scenario.method)
    require_positive(trials=args.trials, workers=args.workers)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jsonl = out / "trials.jsonl"
    done = read_trials(jsonl)
    have = {(s["method"], int(s["trial_seed"])) for s in done}
    wanted = [(m, args.seed + k) for k in range(args.trials) for m in methods]
    todo = [(str(path), seed, m, not args.nominal, texts) for m, seed in wanted if (m, seed) not in have]
    executor = "pool" if args.ray is None else f"ray ({args.ray})"
    print(
        f"sweep: {len(have)} trials already in {jsonl}, {len(todo)} to run on {args.workers} {executor} worker(s)",
        file=sys.stderr,
    )
    results = pool_results(todo, args.workers) if args.ray is None else ray_results(todo, args.ray, args.workers)
    wall0 = time.perf_counter()
    ran, interrupted = 0, False
    with pool.sigterm_as_interrupt(), jsonl.open("a") as fh:
        try:
            for summary in results:
                fh.write(json.dumps(summary, default=float) + "\n")
                fh.flush()
                os.fsync(fh.fileno())
                done.append(summary)
                ran += 1
                outcome = "ok" if summary["success"] else summary["failure"]
                print(
                    f"[{ran}/{len(todo)}] {summary['method']} seed {summary['trial_seed']}: {outcome}", file=sys.stderr
                )
        except KeyboardInterrupt:
            interrupted = True
        finally:
            results.close()  # stops the workers (pool terminated, Ray tasks cancelled)
    wall = time.perf_counter() - wall0
    keys = set(wanted)
    trials = [s for s in done if (s["method"], int(s["trial_seed"])) in keys]
    agg = aggregate(trials)
    if len(methods) > 1:
        agg["by_method"] = {m: aggregate([s for s in trials if s["method"] == m]) for m in methods}
    agg.update(
        wall_time_s=wall,
        trials_run=ran,
        trials_per_minute=60.0 * ran / wall if ran else float("nan"),
        workers=args.workers,
        executor=executor,
        planner_budget=scenario.planner.budget,
        complete=len(trials) == len(wanted),
    )
    (out / "aggregate.json").write_text(json.dumps(agg, indent=2, default=float))
    flagged = set(_flagged(agg))
    replays = [replay_command(path, s, texts) for s in trials if s["trial_seed"] in flagged and "error" not in s]
    text = report_markdown(agg, scenario.name, methods, replays=replays)
    (out / "report.md").write_text(text)
    print(text)
    if interrupted:
        print(
            f"sweep: interrupted; {len(trials)} of {len(wanted)} trials kept in {jsonl}: rerun to resume",
            file=sys.stderr,
        )
        return 1
    return 0  # completed: the trials' failures are data (aggregate.json, report.md), not the sweep's
