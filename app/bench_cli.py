"""`safesysid bench --out DIR`: every benchmarks/bench_*.py module's run(quick) into bench.json;
modules whose run() takes `out` write their scaling plots (PNG) to DIR; the README tables go to
DIR/bench.md (benchmarks/readme_table.py)."""

import argparse
import importlib
import inspect
import json
import pkgutil
import sys
import time
import traceback
from pathlib import Path

import safesysid.benchmarks as benchmarks


def cmd_bench(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    failed = False
    for info in sorted(pkgutil.iter_modules(benchmarks.__path__), key=lambda m: m.name):
        if not info.name.startswith("bench_"):
            continue
        name = info.name[len("bench_") :]
        print(f"bench {name} ...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        try:
            module = importlib.import_module(f"safesysid.benchmarks.{info.name}")
            kwargs = {"out": out} if "out" in inspect.signature(module.run).parameters else {}
            results[name] = module.run(quick=args.quick, **kwargs)
        except Exception as err:  # a broken benchmark is reported, the others still run
            failed = True
            results[name] = {"error": f"{type(err).__name__}: {err}", "traceback": traceback.format_exc()}
        results[name]["bench_wall_time_s"] = time.perf_counter() - t0
    path = out / "bench.json"
    path.write_text(json.dumps(results, indent=2, default=float))
    print(
        json.dumps(
            {k: {kk: vv for kk, vv in v.items() if kk != "traceback"} for k, v in results.items()},
            indent=2,
            default=float,
        )
    )
    from safesysid.benchmarks.readme_table import load_line, tables

    (out / "bench.md").write_text(tables(results) + "\n\n" + load_line(results) + "\n")
    print(f"wrote {path}, {out / 'bench.md'}", file=sys.stderr)
    return 1 if failed else 0
