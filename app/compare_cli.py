"""`safesysid compare`: methods x dumbbells x trials on a local process pool, summarised in the
row format of the paper's Table III (README.md, "Commands").

A cell of the table (one method, one experiment = one scenario) is, in this order:
  collide        any run collided (the referee's independent geometry), whatever the dumbbell;
  fail at 6lb    no collision, and 6lb is the lightest dumbbell with a failed run (any trial);
  success        every run of every dumbbell succeeded.
The paper's table never shows a method that both collides and fails otherwise; a collision is
the safety violation, so it ranks first. Runs stream to DIR/runs.jsonl: an interrupted compare
(Ctrl-C) writes the table of what finished, and a rerun with the same DIR resumes.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from safesysid.cli import BadInput, require_positive
from safesysid.systems.config import Scenario

TABLE_FILES = ("table.md", "table.csv", "table.json", "table.png")
# runs.csv: one line per run (what the former per-run table.csv held)
SUMMARY_COLUMNS = (
    "method trial seed success failure collisions min_clearance_m max_torque_ratio max_tracking_error_rad"
    " tracking_bound_rad contains_truth cond_Y mass_estimate_kg mass_width_kg brakes median_solve_s wall_time_s"
    " task_certified_torque_ratio task_robust_active_fraction task_max_lambda_Nm task_duration_s task_time_scale"
).split()


def dumbbell_catalogue(scenario: Scenario) -> dict[str, float]:
    """{name: mass_kg} of the scenario's dumbbells file, lightest first."""
    from safesysid.systems.model.loading import resolve_path, scenario_dir
    from safesysid.systems.model.payload import load_dumbbells

    bells = load_dumbbells(resolve_path(scenario.payload.dumbbells_file, scenario_dir(scenario)))
    return dict(sorted(((name, b.mass_kg) for name, b in bells.items()), key=lambda kv: kv[1]))


def parse_dumbbells(text: str | None, catalogue: dict[str, float], default: str) -> list[str]:
    """`4lb,6lb` (a list) or `4lb..8lb` (every dumbbell whose mass lies between the two), lightest
    first; None: the scenario's own dumbbell."""
    if not text:
        return [default]
    names = list(catalogue)
    if ".." in text:
        lo, _, hi = (x.strip() for x in text.partition(".."))
        for end in (lo, hi):
            if end not in catalogue:
                raise BadInput(f"--dumbbells: {end!r} is not one of {', '.join(names)}")
        m_lo, m_hi = sorted((catalogue[lo], catalogue[hi]))
        return [n for n in names if m_lo <= catalogue[n] <= m_hi]
    chosen = [x.strip() for x in text.split(",") if x.strip()]
    for name in chosen:
        if name not in catalogue:
            raise BadInput(f"--dumbbells: {name!r} is not one of {', '.join(names)}")
    return sorted(dict.fromkeys(chosen), key=catalogue.__getitem__)


def parse_methods(text: str) -> list[str]:
    """`all` (every name of systems/config.METHODS) or a comma-separated list of them."""
    from safesysid.systems.config import METHODS

    if text.strip() == "all":
        return list(METHODS)
    methods = list(dict.fromkeys(m.strip() for m in text.split(",") if m.strip()))
    for m in methods:
        if m not in METHODS:
            raise BadInput(f"--methods: {m!r} is not one of all, {', '.join(METHODS)}")
    if not methods:
        raise BadInput("--methods: empty")
    return methods


def cell(runs: list[dict], dumbbells: list[str], expected: int) -> str:
    """The Table III cell of one method from its run records ({dumbbell, success, collisions,
    failure}); dumbbells lightest first; expected: the number of runs the cell stands for."""
    if any(r["collisions"] > 0 or r["failure"] == "collision" for r in runs):
        return "collide"
    for name in dumbbells:
        if any(not r["success"] for r in runs if r["dumbbell"] == name):
            return f"fail at {name}"
    if len(runs) < expected:
        return f"incomplete ({len(runs)}/{expected} runs, all succeeded)"
    return "success"


def stack_layer(dumbbells: list[str], dumbbell: str, stack: bool) -> list[str]:
    """--stack: the scenario layer of `dumbbell`'s runs, with the lighter dumbbells of the list
    already on the platform (the paper stacks them in order); [] without --stack."""
    below = dumbbells[: dumbbells.index(dumbbell)]
    return [f"task: {{stack_on: [{', '.join(below)}]}}"] if stack and below else []


def run_folder(out: Path, method: str, dumbbell: str, *, trial: int) -> Path:
    return out / method / dumbbell / f"trial{trial}"


def run_one(scenario_path: str, scenario_text: list, method: str, dumbbell: str, trial: int, out: str) -> dict:
    """One run in a worker process: the scenario with that dumbbell, seed = scenario seed + trial;
    its folder gets the full output of `safesysid run`. Returns the summary with its keys."""
    from safesysid.online import run_online
    from safesysid.scenario import load_scenario

    scenario = load_scenario(scenario_path, overrides=[*scenario_text, f"payload: {{dumbbell: {dumbbell}}}"])
    folder = run_folder(Path(out), method, dumbbell, trial=trial)
    summary = run_online(scenario, folder, method=method, seed=scenario.seed + trial)
    summary.update(dumbbell=dumbbell, trial=trial, folder=str(folder.relative_to(out)))
    return summary


def _key(s: dict) -> tuple:
    return s["method"], s["dumbbell"], int(s["trial"])


def table(done: list[dict], methods: list[str], dumbbells: list[str], *, trials: int) -> dict:
    """table.json: per method its cell and, per dumbbell, successes and failures by reason."""
    rows = {}
    for m in methods:
        runs = [s for s in done if s["method"] == m and s["dumbbell"] in dumbbells and s["trial"] < trials]
        per = {}
        for d in dumbbells:
            mine = [s for s in runs if s["dumbbell"] == d]
            failures = {}
            for s in mine:
                if not s["success"]:
                    failures[s["failure"]] = failures.get(s["failure"], 0) + 1
            per[d] = {"runs": len(mine), "success": sum(bool(s["success"]) for s in mine), "failures": failures}
        rows[m] = {"cell": cell(runs, dumbbells, len(dumbbells) * trials), "per_dumbbell": per}
        rows[m]["task"] = {d: [task_played(s) for s in sorted(runs, key=_key) if s["dumbbell"] == d] for d in dumbbells}
    return rows


def task_played(summary: dict) -> dict:
    """What the task phase played in one run: its duration and time scale (None: not played),
    refused (task_uncertified), the certificate executed (at the cap when refused; None: no ARMOUR
    certificate) and whether the box it was computed with holds the payload."""
    task = summary.get("task") or {}
    keys = ("duration_s", "time_scale", "certified_torque_ratio", "certificate_box_contains_payload")
    return {"refused": bool(task.get("uncertified")), **{k: task.get(k) for k in keys}}


def _task_text(played: list[dict]) -> str:
    """One table cell: each trial's task duration, scale and certificate, or `refused`."""
    texts = []
    for p in played:
        ratio = p["certified_torque_ratio"]
        cert = "" if ratio is None else f"certificate {ratio:.3f}"
        if p["certificate_box_contains_payload"] is False and ratio is not None:
            cert += ", box excludes the payload"
        if p["refused"]:
            texts.append(f"refused: task_uncertified ({cert} at the cap)")
        elif p["duration_s"] is None:
            texts.append("not played")
        else:
            texts.append(f"{p['duration_s']:.2f} s ({p['time_scale']:g}x{', ' + cert if cert else ''})")
    return "; ".join(texts) or "-"


def _per_dumbbell_text(entry: dict) -> str:
    text = f"{entry['success']}/{entry['runs']}"
    if entry["failures"]:
        text += " (" + ", ".join(f"{k} {v}" for k, v in sorted(entry["failures"].items())) + ")"
    return text


def write_tables(out: Path, scenario_name: str, rows: dict, *, dumbbells: list[str], trials: int) -> None:
    """table.md / table.csv / table.json: one row per method, the Table III cell of this
    experiment, then successes/runs per dumbbell with the failures by reason."""
    head = ["method", scenario_name, *dumbbells]
    lines = [
        f"# {scenario_name}: {len(rows)} methods, dumbbells {', '.join(dumbbells)}, {trials} trial(s) each",
        "",
        "Cell as in the paper's Table III: `collide` (any run collided), `fail at N lb` (lightest",
        "dumbbell with a failed run), `success`. Per dumbbell: successful runs / runs (failures).",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    csv_rows = []
    for m, row in rows.items():
        per = [_per_dumbbell_text(row["per_dumbbell"][d]) for d in dumbbells]
        lines.append("| " + " | ".join([m, row["cell"], *per]) + " |")
        csv_rows.append([m, row["cell"], *per])
    lines += [
        "",
        "Task phase per dumbbell: the task trajectory's duration as played, its time scale and ARMOUR's",
        "torque certificate with the box latched at the switch (slowed until the certificate is <= 1, up",
        "to task.max_time_scale; refused: no scale did).",
        "",
        "| " + " | ".join(["method", *dumbbells]) + " |",
        "|" + "---|" * (len(dumbbells) + 1),
    ]
    for m, row in rows.items():
        lines.append("| " + " | ".join([m, *(_task_text(row.get("task", {}).get(d, [])) for d in dumbbells)]) + " |")
    (out / "table.md").write_text("\n".join(lines) + "\n")
    with (out / "table.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(head)
        writer.writerows(csv_rows)
    doc = {"scenario": scenario_name, "dumbbells": dumbbells, "trials": trials, "methods": rows}
    (out / "table.json").write_text(json.dumps(doc, indent=2))


def row_of(summary: dict, trial: int) -> dict:
    est = summary["estimate"]
    times = sorted(summary["planner"]["solve_time_s"])
    task_robust = (summary.get("robust_input") or {}).get("task") or {}
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
        "task_certified_torque_ratio": (summary.get("task") or {}).get("certified_torque_ratio"),
        # how hard ARMOUR's robust input worked in the task phase (None: another controller)
        "task_robust_active_fraction": task_robust.get("active_fraction"),
        "task_max_lambda_Nm": task_robust.get("max_lambda_Nm"),
        "task_duration_s": (summary.get("task") or {}).get("duration_s"),  # as played (None: not played)
        "task_time_scale": (summary.get("task") or {}).get("time_scale"),
    }


def write_runs_csv(out: Path, done: list[dict]) -> None:
    """runs.csv: one line per run (the per-run columns of `safesysid run`'s headline)."""
    columns = ["dumbbell", *SUMMARY_COLUMNS, "phase", "placement_error_m", "folder"]
    with (out / "runs.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        for s in sorted(done, key=_key):
            writer.writerow({**s, **row_of(s, s["trial"])})


def cmd_compare(args: argparse.Namespace) -> int:
    from safesysid import figures, table_iv
    from safesysid.pool import read_jsonl, run_streamed
    from safesysid.run_cli import scenario_path
    from safesysid.scenario import load_scenario
    from safesysid.systems.model.loading import robot_from_scenario

    path = scenario_path(args)
    scenario = load_scenario(path, overrides=args.scenario_text)  # exit 2 on bad input before any worker starts
    methods = parse_methods(args.methods)
    dumbbells = parse_dumbbells(args.dumbbells, dumbbell_catalogue(scenario), scenario.payload.dumbbell)
    require_positive(trials=args.trials, workers=args.workers)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jsonl = out / "runs.jsonl"
    # Earlier runs of other scenario layers would not be these runs: resume only the same setup.
    setup = {"scenario": str(path.resolve()), "scenario_text": list(args.scenario_text), "stack": bool(args.stack)}
    setup_file = out / "setup.json"
    if setup_file.exists() and json.loads(setup_file.read_text()) != setup:
        raise BadInput(f"--out: {out} holds a compare of another scenario or --scenario-text; use a new folder")
    setup_file.write_text(json.dumps(setup, indent=2))
    done = [s for s in read_jsonl(jsonl, _key) if s.get("scenario") == scenario.name]
    have = {_key(s) for s in done}
    jobs = [
        (str(path), list(args.scenario_text) + stack_layer(dumbbells, d, args.stack), m, d, k, str(out))
        for k in range(args.trials)
        for d in dumbbells
        for m in methods
        if (m, d, k) not in have
    ]
    print(
        f"compare: {len(have)} runs already in {jsonl}, {len(jobs)} to run on {args.workers} worker(s)", file=sys.stderr
    )

    def note(job: tuple, s: dict) -> str:
        return f"{job[2]} {job[3]} trial {job[4]}: {'success' if s['success'] else s['failure']}"

    try:
        _, interrupted = run_streamed(run_one, jobs, args.workers, jsonl=jsonl, describe=note, label="compare")
    finally:  # a run that raised still leaves the table of those that finished (they are in runs.jsonl)
        done = [s for s in read_jsonl(jsonl, _key) if s.get("scenario") == scenario.name]
        rows = table(done, methods, dumbbells, trials=args.trials)
        write_tables(out, scenario.name, rows, dumbbells=dumbbells, trials=args.trials)
        write_runs_csv(out, done)
        figures.table_figure(out / "table.png", scenario.name, rows, dumbbells=dumbbells)
        limit = robot_from_scenario(scenario).joint_params.torque_limit
        figures.compare_figures(out, [s for s in done if s["method"] in methods and s["dumbbell"] in dumbbells], limit)
        prior = (scenario.initial_interval.lower, scenario.initial_interval.upper)
        chosen = [s for s in done if s["method"] in methods and s["trial"] < args.trials]
        table_iv.write_identification_results(out, scenario.name, chosen, dumbbells=dumbbells, prior=prior)
        print(f"wrote {', '.join(str(out / f) for f in TABLE_FILES)}, runs.csv, figures", file=sys.stderr)
    print((out / "table.md").read_text())
    return 130 if interrupted else 0
