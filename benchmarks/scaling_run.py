"""Only the scaling parts of `safesysid bench` (full size), into OUT/bench.json, OUT/bench.md and
the PNGs — what the README's bench tables come from (the whole `safesysid bench` also runs the
long fixed-size benches: planner priors x solvers, task trajectories, the diagnosis self-check):

    python -m safesysid.benchmarks.scaling_run out/bench [--quick]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path


def main(argv=None) -> int:
    from safesysid.benchmarks import bench_diagnose, bench_estimator, bench_planner, bench_regressors, bench_sim
    from safesysid.benchmarks.readme_table import load_line, tables

    argv = sys.argv[1:] if argv is None else argv
    quick = "--quick" in argv
    paths = [a for a in argv if not a.startswith("--")]
    out = Path(paths[0] if paths else "out/bench")
    out.mkdir(parents=True, exist_ok=True)
    parts = {
        "sim": lambda: bench_sim.run(quick, out),
        "planner": lambda: {"scaling": bench_planner.scaling(quick, out)},
        "estimator": lambda: {"scaling": bench_estimator.scaling(quick, out)},
        "regressors": lambda: {"scaling": bench_regressors.scaling(quick, out)},
        "diagnose": lambda: {"scaling": bench_diagnose.scaling(quick, out)},
    }
    results = {}
    for name, run in parts.items():
        t0 = time.perf_counter()
        results[name] = run()
        results[name]["bench_wall_time_s"] = time.perf_counter() - t0
        print(f"{name}: {results[name]['bench_wall_time_s']:.0f} s", file=sys.stderr, flush=True)
        (out / "bench.json").write_text(json.dumps(results, indent=2, default=float))
    text = tables(results) + "\n\n" + load_line(results) + "\n"
    (out / "bench.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
