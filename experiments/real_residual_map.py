"""Where the real Gen3 gap left after the correction lies, and whether a further candidate
explains part of it: nested leave-one-run-out on the shared real runs (the diagnose CLI's
reports, each with its residual map in report.html), then each candidate of
systems/diagnosis/candidates.py fitted on each fold's fit logs and scored on its held-out run.

    python experiments/real_residual_map.py [--out out/real_map]

Skips (exit 0) when ../shared/data/kinova_gen3_real is absent.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

SHARED = Path(__file__).resolve().parents[2] / "shared"
RUNS = [SHARED / "data" / "kinova_gen3_real" / f"run{k}.csv" for k in (1, 2, 3)]
URDF = SHARED / "models" / "reference" / "kinova_gen3_raptor_nomesh.urdf"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/real_map")
    args = parser.parse_args(argv)
    if not all(p.is_file() for p in RUNS + [URDF]):
        print(f"skipped: the shared real runs or reference URDF are absent ({RUNS[0].parent})")
        return 0
    from safesysid.diagnose_cli import leave_one_out_folds
    from safesysid.diagnose_report import residual_map_lines
    from safesysid.systems.diagnosis.candidates import CANDIDATES, candidate_gain
    from safesysid.systems.diagnosis.problem import design_residual
    from safesysid.systems.model.robot_model import load_robot

    out = Path(args.out)
    folds, pooled = leave_one_out_folds(load_robot(model_path=URDF), RUNS, out, model_path=URDF)
    p = pooled["pooled"]
    print(f"held-out RMS pooled over the folds {p['rms_before']:.3f} -> {p['rms_after']:.3f} N·m")
    print("\n".join(residual_map_lines(pooled["residual_map_after"])))
    print("\n| candidate | held-out run | RMS left [N·m] | with the candidate | reduction |\n|---|---|---|---|---|")
    for kind in CANDIDATES:
        for d in folds:
            fit = [(f, design_residual(f, d.combined_params)) for f in d.fit_designs]
            g = candidate_gain(fit, list(zip(d.check_designs, d.check_residual_after)), kind)
            run = Path(d.check_designs[0].source).name
            red = 1 - g["rms_after"] / g["rms_before"]
            print(f"| {kind} | {run} | {g['rms_before']:.3f} | {g['rms_after']:.3f} | {100 * red:.1f} % |")
    print(f"wrote {out}/report.html (pooled residual map) and one folder per fold")
    return 0


if __name__ == "__main__":
    sys.exit(main())
