"""Planner feasibility under the Table II prior: 10 random starts near the default pose (3 boxes
near the arm, 4 lb payload), V_max 0.005 (scenario) and 0.02 (hardware); first plan from rest.
Prints, per V_max: feasible starts, mean allowed k-box half-width (fraction of k_range), median
wall and CPU time of the planning call, and the reasons of the failures.

Compare two versions of the code: `python benchmarks/bench_torque_feasibility.py [PACKAGE_ROOT]`,
PACKAGE_ROOT a folder holding another `safesysid` package (e.g. an exported older commit laid
out as safesysid/, safesysid/systems/, ...), imported instead of the installed one.
"""

from __future__ import annotations

import json
import os
import sys


def run(quick: bool = False) -> dict:
    import numpy as np
    from safesysid.benchmarks.bench_planner import Q0, near_boxes, table_ii_box
    from safesysid.systems.config import Planner
    from safesysid.systems.controller import armour as ctl
    from safesysid.systems.model.payload import load_dumbbells
    from safesysid.systems.model.robot_model import MODELS_DIR, load_robot
    from safesysid.systems.planner.safe_planner import SafePlanner

    robot = load_robot(coulomb_smoothing=0.01)
    payload = load_dumbbells(MODELS_DIR / "dumbbells.yaml")["4lb"]
    theta0, lo, hi = table_ii_box(robot)
    out = {"load_average_at_start": os.getloadavg()[0]}
    for V_max in (0.005, 0.02):
        bounds = ctl.tracking_bounds_for(robot, ctl.ArmourGains(np.array([5.0] * 4 + [7.0] * 3), 20.0, V_max), lo)
        feasible, times, cpus, box, reasons = 0, [], [], [], []
        for start in range(10):
            rng = np.random.default_rng(100 + start)
            q = Q0 + rng.uniform(-0.3, 0.3, 7) * np.array([1, 0.5, 1, 0.5, 1, 0.5, 1])
            planner = SafePlanner(
                robot, Planner(), obstacles=near_boxes(robot, q, rng, payload=payload), payload=payload, tracking=bounds
            )
            res = planner.plan(q, np.zeros(7), np.zeros(7), theta0, lo, hi)
            times.append(res.solve_time_s)
            cpus.append(res.details.get("cpu_time_s", np.nan))
            if res.ok:
                feasible += 1
                box.append(float(np.mean(res.k_box[1] - res.k_box[0]) / 2))
            else:
                reasons.append(res.reason)
        out[f"V_max_{V_max}"] = {
            "feasible": feasible,
            "starts": 10,
            "mean_k_box_fraction": float(np.mean(box)) if box else None,
            "median_wall_s": float(np.median(times)),
            "median_cpu_s": float(np.median(cpus)),
            "reasons": reasons,
        }
    return out


if __name__ == "__main__":
    if len(sys.argv) > 1:
        sys.path.insert(0, sys.argv[1])
    print(json.dumps(run(), indent=1))
