"""Real-time factor of the closed loop: real arm (1 kHz discrete MultibodyPlant, friction,
sensor) + ARMOUR controller (interval bounds over all 14 n parameters) + Bezier source.

Target: real-time factor >= 1 (simulated seconds per wall-clock second), loggers included.
On a shared machine the wall-clock factor depends on the load (reported); the CPU-time factor
does not. Also reports the per-step cost of the controller law alone and of the baselines' loops.
"""

from __future__ import annotations

import time

import numpy as np
from safesysid.closed_loop import build_closed_loop, simulate_closed_loop
from safesysid.scenario import load_scenario, robot_from_scenario
from safesysid.systems import armour as C
from safesysid.systems.bezier import QuinticBezier

TARGET_RTF = 1.0


def _loop_rtf(s, robot, theta0, box, kind, sim_s, repeat):
    q0 = np.array(s.q0_rad)
    q_end = q0 + np.array(s.planner.k_range_rad) * np.linspace(-1, 1, robot.n)
    trajectory = (QuinticBezier(q0, np.zeros(robot.n), np.zeros(robot.n), s.planner.duration_s), q_end)
    best, best_cpu = np.inf, np.inf
    for _ in range(repeat):
        loop = build_closed_loop(s, trajectory, theta0, box, kind=kind, robot=robot)
        t0, c0 = time.perf_counter(), time.process_time()
        simulate_closed_loop(loop, q0, sim_s)
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return sim_s / best, sim_s / best_cpu


def _load():
    try:
        import os

        return os.getloadavg()[0]
    except (OSError, AttributeError):
        return None


def run(quick: bool = False) -> dict:
    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}})
    robot = robot_from_scenario(s)
    ii = s.initial_interval
    theta0, box = C.parameter_box(robot, ii.nominal, ii.lower, ii.upper)
    sim_s = 1.0 if quick else 3.0
    repeat = 1 if quick else 2
    result = {"sim_time_s": sim_s, "time_step_s": s.plant.time_step_s, "target_real_time_factor": TARGET_RTF}
    rtf, rtf_cpu = _loop_rtf(s, robot, theta0, box, "armour", sim_s, repeat)
    result["armour_real_time_factor"] = rtf
    # CPU-time based: what the loop costs when it has a core to itself (shared CI machines).
    result["armour_cpu_real_time_factor"] = rtf_cpu
    result["load_average_1min"] = _load()
    result["meets_target"] = bool(rtf >= TARGET_RTF)
    # The law alone (one evaluation = one control step).
    dyn = C.ControllerDynamics(robot)
    gains = C.ArmourGains(np.asarray(s.controller.Kr, float), s.controller.alpha, s.controller.V_max)
    rng = np.random.default_rng(0)
    q, v = rng.normal(size=(2, robot.n))
    count = 300 if quick else 2000
    t0 = time.process_time()
    for _ in range(count):
        C.armour_control(dyn, gains, q, v, q + 0.01, v, v, theta0, box)
    result["armour_law_cpu_us_per_step"] = (time.process_time() - t0) / count * 1e6
    if not quick:
        for kind in ("pid", "adaptive", "adaptive_robust"):
            result[f"{kind}_real_time_factor"], result[f"{kind}_cpu_real_time_factor"] = _loop_rtf(
                s, robot, theta0, box, kind, sim_s, 1
            )
    return result


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
