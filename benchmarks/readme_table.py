"""The README's bench tables from a bench.json (`safesysid bench` writes them to bench.md too):

    python -m safesysid.benchmarks.readme_table out/bench/bench.json

Each table is printed only when its benchmark is in the file (and did not fail)."""

from __future__ import annotations

import json
import sys
from pathlib import Path


def _f(x, digits=2):
    return "–" if x is None else f"{x:.{digits}f}"


def _table(header, rows):
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows])


def sim_table(sim):
    rows = [
        ("plant alone", _f(sim["plant_alone_real_time_factor"]), _f(sim["plant_alone_cpu_real_time_factor"]), "–"),
        (
            "ours (ARMOUR, fast path)",
            _f(sim["armour_real_time_factor"]),
            _f(sim["armour_cpu_real_time_factor"]),
            _f(sim.get("armour_law_cpu_us_per_step"), 0),
        ),
        (
            "ours, reference law (before)",
            _f(sim["armour_reference_real_time_factor"]),
            _f(sim["armour_reference_cpu_real_time_factor"]),
            _f(sim.get("armour_law_reference_cpu_us_per_step"), 0),
        ),
    ]
    if "armour_loop_law_replayed_cpu_us_per_step" in sim:
        rows.append(
            (
                "ours, law replayed (the loop around the law)",
                "–",
                _f(1e3 / sim["armour_loop_law_replayed_cpu_us_per_step"]),
                _f(sim["armour_law_in_loop_cpu_us_per_step"], 0) + " in the loop",
            )
        )
    for kind in ("pid", "adaptive", "adaptive_robust"):
        if f"{kind}_real_time_factor" in sim:
            rows.append((kind, _f(sim[f"{kind}_real_time_factor"]), _f(sim[f"{kind}_cpu_real_time_factor"]), "–"))
    for method, m in sim.get("online_by_method", {}).items():
        rows.append((f"online diagram, {method}", _f(m["real_time_factor"]), _f(m["cpu_real_time_factor"]), "–"))
    head = ("closed loop (1 kHz)", "real-time factor (wall)", "real-time factor (CPU)", "law µs/step (CPU)")
    return _table(head, rows)


def _timing_rows(rows):
    return [
        (k, r["count"], _f(r["median_s"]), _f(r["p95_s"]), _f(r["max_s"]), r["missed"], r.get("feasible", "–"))
        for k, r in rows.items()
    ]


def planner_tables(planner):
    sc = planner["scaling"]
    head = ("median [s]", "p95 [s]", "max [s]", "missed 1.5 s", "feasible")
    obstacles = _table(("obstacles", "solves", *head), _timing_rows(sc["vs_obstacles"]))
    n_s = _table(("N_s (= time intervals)", "solves", *head), _timing_rows(sc["vs_N_s"]))
    return obstacles + "\n\n" + n_s


def estimator_table(est):
    rows = [
        (k, r["samples"], r["segments"], _f(r["wall_s"]), _f(r["cpu_s"]), _f(r["cpu_us_per_sample"], 1))
        for k, r in est["scaling"]["vs_length_s"].items()
    ]
    head = ("data [s] at 1 kHz", "samples", "segments", "update wall [s]", "update CPU [s]", "CPU µs/sample")
    return _table(head, rows)


def regressor_table(reg):
    sc = reg["scaling"]
    rows = [
        (
            b,
            _f(r["ours_We_us"], 1),
            _f(r["ours_W_full_us"], 1),
            _f(r.get("ours_controller_Wp_Wm_us"), 1),
            _f(r["drake_autodiff_We_us"], 1),
            _f(r.get("pinocchio_W_full_us"), 1),
        )
        for b, r in sc["vs_batch"].items()
    ]
    head = (
        "batch",
        "ours W_e µs/sample",
        "ours full W",
        "ours one-sample Wp + Wm (controller)",
        "Drake AutoDiffXd W_e",
        "Pinocchio full W",
    )
    return _table(head, rows) + f"\n\nPinocchio: {sc['pinocchio']}."


def diagnose_table(diag):
    sc = diag["scaling"]
    rows = [
        (r["logs"], r["samples"], _f(r["wall_s"]), _f(r["cpu_s"]), ", ".join(r["cause"]) or "none")
        for part in ("vs_samples", "vs_logs")
        for r in sc[part].values()
    ]
    return _table(("logs", "samples per log", "wall [s]", "CPU [s]", "cause found"), rows)


SECTIONS = {
    "sim": ("Closed-loop simulation speed", sim_table),
    "planner": ("Planner solve time", planner_tables),
    "estimator": ("Estimator update time", estimator_table),
    "regressors": ("Regressor time per sample", regressor_table),
    "diagnose": ("Gap diagnosis time", diagnose_table),
}


def tables(results: dict) -> str:
    """Markdown of every benchmark present in `results` (bench.json's content)."""
    parts = []
    for name, (title, make) in SECTIONS.items():
        part = results.get(name)
        if not part or "error" in part:
            continue
        try:
            parts.append(f"**{title}**\n\n{make(part)}")
        except KeyError:  # an older bench.json without the scaling fields
            continue
    return "\n\n".join(parts)


def load_line(results: dict) -> str:
    parts = [v for v in results.values() if isinstance(v, dict)]
    parts += [v["scaling"] for v in parts if isinstance(v.get("scaling"), dict)]
    loads = [x for v in parts for k, x in v.items() if k.startswith("load_average") and x is not None]
    return f"Load average during the run: {min(loads):.1f}-{max(loads):.1f} on 2 cores." if loads else ""


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m safesysid.benchmarks.readme_table BENCH_JSON", file=sys.stderr)
        return 2
    path = Path(argv[0])
    try:
        results = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        print(f"{path}: cannot read bench results ({err})", file=sys.stderr)
        return 2
    print(tables(results))
    print()
    print(load_line(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
