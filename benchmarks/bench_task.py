"""Task trajectories of the paper's experiments (scenarios/experiment_{a,b,c}.yaml): solve time
with SNOPT and with Ipopt (each alone, no fallback, no cache), and the independent verification
of each answer (Drake signed distance on the link shapes + payload, Drake inverse dynamics at
1 kHz), plus the ARMOUR certificate's torque bound over the tube (reachability's interval RNEA)
for two parameter boxes: the 8 lb payload known exactly (rest of the robot +-5 %: the best an
identification can give) and the paper's Table II prior (what `conservative` runs with).

    python benchmarks/bench_task.py            # prints JSON and a table
"""

from __future__ import annotations

import json
import os
import sys
import time


def _certified(prob, scenario, trajectory):
    from safesysid.online import prior
    from safesysid.systems.model.uncertainty import parameter_box
    from safesysid.systems.task import check as task_check

    ee = prob.theta[prob.robot.ee_slice]
    exact0, exact = parameter_box(prob.robot, ee, ee, ee, rest_ratio=0.05, friction_ratio=0.05)
    table0, table = prior(prob.robot, scenario, "conservative")
    return {
        "exact_payload": task_check.certified_torque_ratio(prob, trajectory, exact0, exact.lo, exact.hi)[0],
        "table_ii_prior": task_check.certified_torque_ratio(prob, trajectory, table0, table.lo, table.hi)[0],
    }


def run(quick: bool = False) -> dict:
    from safesysid.scenario import SCENARIOS_DIR, load_scenario
    from safesysid.systems.task import check as task_check
    from safesysid.systems.task import trajectory as tt

    out = {"load_average_at_start": os.getloadavg()[0], "cpus": os.cpu_count()}
    for name in ("experiment_a", "experiment_b", "experiment_c"):
        scenario = load_scenario(SCENARIOS_DIR / f"{name}.yaml")
        prob = tt.task_problem_from_scenario(scenario)
        rows = {}
        for solver in ("snopt", "ipopt"):
            t0 = time.process_time()
            res = tt.solve_task_trajectory(prob, solver=solver, fallback=False)
            row = {
                "status": res.status,
                "solver_status": res.solver_status,
                "solve_time_s": res.solve_time_s,
                "cpu_time_s": time.process_time() - t0,
                "rounds": res.details["attempts"][0]["rounds"],
                "cost": res.cost,
                "min_sphere_clearance_m": res.min_sphere_clearance_m,
                "sampled_torque_ratio": res.max_torque_ratio,
            }
            if res.ok:
                check = task_check.verify_task_trajectory(prob, res.trajectory)
                row.update(
                    verified=check.ok,
                    min_clearance_m=check.min_clearance_m,
                    closest_pair=check.closest_pair,
                    max_torque_ratio=check.max_torque_ratio,
                    max_velocity_ratio=check.max_velocity_ratio,
                    max_joint_limit_ratio=check.max_joint_limit_ratio,
                    placement_error_m=check.placement_error_m,
                    certified_torque_ratio=_certified(prob, scenario, res.trajectory),
                )
            rows[solver] = row
        out[name] = rows
    out["load_average_at_end"] = os.getloadavg()[0]
    return out


def table(result):
    lines = [
        "| experiment | solver | status | time [s] | jerk cost | link clearance [m] | torque / limit | "
        "certified, exact payload | certified, Table II |",
        "|---" * 9 + "|",
    ]
    for name, rows in result.items():
        if not name.startswith("experiment"):
            continue
        for solver, r in rows.items():
            cert = r.get("certified_torque_ratio", {})
            lines.append(
                f"| {name[-1]} | {solver} | {r['status']} | {r['solve_time_s']:.2f} | {r['cost']:.1f} | "
                f"{r.get('min_clearance_m', float('nan')):.4f} | {r.get('max_torque_ratio', float('nan')):.3f} | "
                f"{cert.get('exact_payload', float('nan')):.3f} | {cert.get('table_ii_prior', float('nan')):.3f} |"
            )
    return "\n".join(lines)


if __name__ == "__main__":
    result = run(quick="--quick" in sys.argv)
    print(json.dumps(result, indent=2, default=str))
    print(table(result))
