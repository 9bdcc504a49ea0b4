"""The identified intervals of a run over LCM against the simulated-clock run of the same scenario
and seed (docs/hardware.md): per parameter the two widths, their ratio, and whether each holds the
arm's true payload (arm-sim's arm_summary.json).

    safesysid run SCENARIO --out SIM                      # simulated clock
    safesysid arm-sim SCENARIO --out ARM &  safesysid run SCENARIO --arm lcm --out RUN
    python experiments/lcm_vs_simulated.py RUN SIM ARM
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

NAMES = ("m", "mcx", "mcy", "mcz", "Ixx", "Ixy", "Ixz", "Iyy", "Iyz", "Izz")


def compare(run_dir: Path, sim_dir: Path, arm_dir: Path) -> list[dict]:
    lcm = json.loads((run_dir / "lcm_run.json").read_text())["estimate"]
    sim = json.loads((sim_dir / "summary.json").read_text())["estimate"]
    truth = np.array(json.loads((arm_dir / "arm_summary.json").read_text())["payload_true"]["theta"])
    if lcm is None:
        raise SystemExit(f"{run_dir / 'lcm_run.json'}: no estimate (no update returned)")
    rows = []
    for k, name in enumerate(NAMES):
        w_lcm = lcm["upper"][k] - lcm["lower"][k]
        w_sim = sim["upper"][k] - sim["lower"][k]
        rows.append(
            dict(
                name=name,
                width_lcm=w_lcm,
                width_sim=w_sim,
                ratio=w_lcm / w_sim if w_sim > 0 else float("nan"),
                truth_in_lcm=bool(lcm["lower"][k] <= truth[k] <= lcm["upper"][k]),
                truth_in_sim=bool(sim["lower"][k] <= truth[k] <= sim["upper"][k]),
            )
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for name in ("run", "sim", "arm"):
        parser.add_argument(name, type=Path)
    args = parser.parse_args()
    rows = compare(args.run, args.sim, args.arm)
    print("| parameter | width over LCM | width, simulated clock | ratio | truth inside (LCM / sim) |")
    print("|---|---|---|---|---|")
    for r in rows:
        inside = f"{'yes' if r['truth_in_lcm'] else 'NO'} / {'yes' if r['truth_in_sim'] else 'NO'}"
        print(f"| {r['name']} | {r['width_lcm']:.4g} | {r['width_sim']:.4g} | {r['ratio']:.2f} | {inside} |")
    within = sum(0.75 <= r["ratio"] <= 1.25 for r in rows)
    print(
        f"\nwidths within ±25 %: {within} of {len(rows)}; truth inside over LCM: {sum(r['truth_in_lcm'] for r in rows)}"
    )


if __name__ == "__main__":
    main()
