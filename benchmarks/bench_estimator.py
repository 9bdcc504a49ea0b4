"""Estimator (Algorithm 1) timing: one update on 7.5 s of 1 kHz data, and an incremental update
on 1.5 s of new data after 6 s already processed (Algorithm 2's cadence).

Targets (2-core machine): full update <= 0.25 s, incremental <= 0.1 s. Best of `repeat`, since
other processes share the cores.
"""

from __future__ import annotations

import copy
import time
from dataclasses import replace

import numpy as np
from safesysid.benchmarks.scaling import load_average, plot, png, timed
from safesysid.systems import estimation as est_mod
from safesysid.systems.model.payload import load_dumbbells, payload_theta_in_end_effector
from safesysid.systems.model.robot_model import MODELS_DIR, load_robot

TARGET_FULL_S = 0.25
TARGET_INCREMENTAL_S = 0.1
CENTRE = [0.0, 0.3, 0.0, 1.5, 0.0, 0.8, 0.0]


def _data(robot, seed=0, duration_s=7.5, rate_hz=1000.0):
    rng = np.random.default_rng(seed)
    db = load_dumbbells(MODELS_DIR / "dumbbells.yaml")["8lb"]
    theta = est_mod.perturbed_robot_theta(rng, robot, 0.05)
    theta[robot.ee_slice] = robot.theta_e + payload_theta_in_end_effector(db, robot.extra["grasp_point"])
    t, q, v, tau, _ = est_mod.simulate_log(rng, robot, theta, duration_s=duration_s, rate_hz=rate_hz, centre=CENTRE)
    return t, q, v, tau


LENGTHS_S = (1.5, 7.5, 30.0, 120.0)


def scaling(quick: bool = False, out=None) -> dict:
    """One full update (add + solve + interval) vs data length at 1 kHz, wall and CPU time (best
    of 2; the data for the longest length is simulated once and cut)."""
    robot = load_robot(coulomb_smoothing=0.01)
    settings = est_mod.EstimatorSettings()
    lengths = LENGTHS_S[:2] if quick else LENGTHS_S
    t, q, v, tau = _data(robot, duration_s=max(lengths))
    rows = {}
    for length in lengths:
        k = int(round(length * 1000))

        def update(k=k):
            e = est_mod.IncrementalEstimator(robot, settings=settings)
            e.add(t[:k], q[:k], v[:k], tau[:k])
            return e.update()

        best = [np.inf, np.inf]
        for _ in range(1 if quick else 2):
            result, wall, cpu = timed(update)
            best = [min(best[0], wall), min(best[1], cpu)]
        rows[str(length)] = {
            "samples": k,
            "segments": int(result.num_segments),
            "wall_s": best[0],
            "cpu_s": best[1],
            "cpu_us_per_sample": 1e6 * best[1] / k,
            "case": result.case,
        }
    return {
        "rate_hz": 1000.0,
        "load_average": load_average(),
        "vs_length_s": rows,
        "plot": plot(
            png(out, "estimator_vs_length"),
            list(lengths),
            {"wall": [r["wall_s"] for r in rows.values()], "CPU": [r["cpu_s"] for r in rows.values()]},
            "data length [s] at 1 kHz",
            "full update [s]",
            "estimator update time vs data length",
            logx=True,
            logy=True,
        ),
    }


def _best(fn, repeat):
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def run(quick: bool = False, out=None) -> dict:
    robot = load_robot(coulomb_smoothing=0.01)
    settings = est_mod.EstimatorSettings()
    repeat = 2 if quick else 5
    t, q, v, tau = _data(robot)
    n_new = int(round(1.5 * 1000))

    def full():
        e = est_mod.IncrementalEstimator(robot, settings=settings)
        t0 = time.perf_counter()
        e.add(t, q, v, tau)
        t1 = time.perf_counter()
        r = e.update()
        return t1 - t0, time.perf_counter() - t1, r

    full_s, (add_s, upd_s, result) = _best(full, repeat)

    base = est_mod.IncrementalEstimator(robot, settings=settings)
    split = len(t) - n_new
    base.add(t[:split], q[:split], v[:split], tau[:split])
    base.update()

    def incremental():
        e = copy.deepcopy(base)
        t0 = time.perf_counter()
        e.add(t[split:], q[split:], v[split:], tau[split:])
        return time.perf_counter() - t0, e.update()

    def timed_incremental():
        e = copy.deepcopy(base)
        t0 = time.perf_counter()
        e.add(t[split:], q[split:], v[split:], tau[split:])
        e.update()
        return time.perf_counter() - t0

    inc_s = min(timed_incremental() for _ in range(repeat))
    _, (inc_add_s, inc_result) = _best(incremental, 1)

    def variant(**kw):
        e = est_mod.IncrementalEstimator(robot, settings=replace(settings, **kw))
        e.add(t, q, v, tau)
        return e.update()

    lp_all_s, lp_all = _best(lambda: variant(set_membership="all"), 2)
    paper_s, paper = _best(lambda: variant(point_estimate="paper", set_membership="none"), 2)
    snopt_s, _ = _best(lambda: variant(solver="snopt"), 2)
    return {
        "samples": int(len(t)),
        "segments": int(result.num_segments),
        "full_update_s": full_s,
        "full_update_add_s": add_s,
        "full_update_solve_and_interval_s": upd_s,
        "full_update_target_s": TARGET_FULL_S,
        "full_update_meets_target": bool(full_s <= TARGET_FULL_S),
        "incremental_update_s": inc_s,
        "incremental_add_s": inc_add_s,
        "incremental_target_s": TARGET_INCREMENTAL_S,
        "incremental_meets_target": bool(inc_s <= TARGET_INCREMENTAL_S),
        "case": result.case,
        "solver": result.solver,
        "cond_Y": result.cond_Y,
        "mass_halfwidth_kg": float(0.5 * (result.upper[0] - result.lower[0])),
        "incremental_case": inc_result.case,
        "full_update_lp_all_s": lp_all_s,
        "mass_halfwidth_lp_all_kg": float(0.5 * lp_all.widths[0]),
        "widths_lp_all": [float(w) for w in lp_all.widths],
        "full_update_paper_only_s": paper_s,
        "mass_halfwidth_paper_only_kg": float(0.5 * paper.widths[0]),
        "full_update_snopt_s": snopt_s,
        "scaling": scaling(quick, out),
    }


def update_cost(log_path: str, scenario_path: str) -> dict:
    """CPU time (process time: the machine's load does not count) of each update on a run's
    log.csv, one update per planner.replan_period_s as the run makes them, with
    estimator.set_membership mass and all (the scenario's other estimator settings and prior;
    one BLAS thread), and the final widths of each."""
    from safesysid.joint_log import read_joint_log
    from safesysid.scenario import load_scenario
    from safesysid.systems.math.blas import single_threaded_blas
    from safesysid.systems.model.loading import robot_from_scenario

    scene = load_scenario(scenario_path)
    robot = robot_from_scenario(scene)
    log = read_joint_log(log_path, robot.n)
    prior, period = scene.initial_interval, scene.planner.replan_period_s
    edges = np.searchsorted(log.t, np.arange(period, log.t[-1] + 1e-9, period), "right")
    out = {}
    for mode in ("mass", "all"):
        settings = replace(est_mod.EstimatorSettings.from_scenario(scene), set_membership=mode)
        est = est_mod.IncrementalEstimator(
            robot,
            settings=settings,
            prior=(np.array(prior.lower), np.array(prior.upper)),
            prior_nominal=np.array(prior.nominal),
        )
        times, start = [], 0
        with single_threaded_blas():
            for stop in edges:
                c0 = time.process_time()
                est.add(log.t[start:stop], log.q[start:stop], log.v[start:stop], log.tau[start:stop])
                result = est.update()
                times.append(time.process_time() - c0)
                start = stop
        out[mode] = {"update_cpu_s": times, "median_s": float(np.median(times)), "widths": result.widths.tolist()}
    return out


if __name__ == "__main__":
    import json
    import sys

    if "--update-cost" in sys.argv:  # --update-cost RUN/log.csv [SCENARIO.yaml (default: quickstart)]
        from safesysid.scenario import SCENARIOS_DIR

        args = sys.argv[sys.argv.index("--update-cost") + 1 :]
        print(
            json.dumps(update_cost(args[0], args[1] if len(args) > 1 else SCENARIOS_DIR / "quickstart.yaml"), indent=2)
        )
    else:
        print(json.dumps(run(quick="--quick" in sys.argv), indent=2, default=float))
