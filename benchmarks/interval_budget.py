"""Where the width of each payload interval comes from (issue 15), and how it scales.

For one synthetic identification run (4 lb payload, the arm's centre pose, a smooth Fourier motion
per joint, torque noise uniform at the declared bound, robot parameters drawn in their ±5 % box):

- Theorem-2 box (least squares, `map` left inverse): its half-width is an exact SUM of four terms,
  torque noise, robot-parameter box θ_r, quadrature (discretisation) and rounding.
- Set-membership LP over all ten parameters (the intersection over all segments): its half-width
  with all sources, and on the same motion's noise-free log with θ_r at nominal, the half-width
  each source gives alone (quadrature always on: the discretisation error is in every log).
- Prior clipping (what the Table II box removes) and physical pruning (J ⪰ 0 and the bounding
  volume of the payload, estimation/physical.py) on top of the LP box.

Swept over the motion amplitude (→ peak joint acceleration) and the data length. Prints one table;
`python -m safesysid.benchmarks.interval_budget [--quick]`. With `--closed-loop N [--workers W]
[--scenario-text YAML]`: the median width / prior width per parameter over N closed-loop seeds of
scenarios/identify_all.yaml (ours and random; published, data-driven and the paper's first-order
interval), the worst data-driven ratio, and where ours' data-driven box is narrower than random's
on the paired seeds. `--save FILE` writes the per-run results as JSON; `--methods ours
--paired-with FILE` runs ours only and pairs it with the other methods' runs of a saved FILE (same
seeds, checked): an option of ours alone then costs half the time, random is not re-run.
"""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
from safesysid.systems import estimation as E
from safesysid.systems.estimation.enclosure import interval_hull, set_membership_bounds
from safesysid.systems.estimation.physical import prune_box
from safesysid.systems.estimation.settings import BoundingVolume
from safesysid.systems.model.inertial import NAMES
from safesysid.systems.model.payload import load_dumbbells, payload_theta_in_end_effector
from safesysid.systems.model.robot_model import MODELS_DIR, load_robot

CENTRE = [0.0, 0.3, 0.0, 1.5, 0.0, 0.8, 0.0]
PRIOR = (np.array([1.2, -0.4, -0.4, -1.0] + [-0.2] * 6), np.array([5.2, 0.4, 0.4, -0.1] + [0.2] * 6))
PRIOR_NOMINAL = np.array([3.2, 0.0, 0.0, -0.5] + [0.0] * 6)
# The 4 lb dumbbell (0.18 m long, heads of radius 0.04 m) at the grasp point, handle along x, with 1 cm to spare.
VOLUME = BoundingVolume("box", np.array([0.0, 0.0, -0.2]), np.array([0.10, 0.05, 0.05]), np.eye(3))
SOURCES = {"torque": "rad_torque", "theta_r": "rad_theta_r", "quadrature": "rad_quad", "rounding": "rad_round"}


def _estimator(robot, t, q, v, tau):
    est = E.IncrementalEstimator(
        robot, settings=E.EstimatorSettings(set_membership="none"), prior=PRIOR, prior_nominal=PRIOR_NOMINAL
    )
    est.add(t, q, v, tau)
    est.update()
    return est


def _lp_half(est, rad_r, box, rows=None):
    st = dataclasses.replace(est.settings, set_membership="all")
    lo, hi, ok = set_membership_bounds(
        rows or est.rows, est.theta_r, rad_r, settings=st, box_lo=box[0], box_hi=box[1], params=range(10)
    )
    return 0.5 * (hi - lo) if ok else np.full(10, np.nan)


def budget(robot, theta_true, amplitude_rad, duration_s, seed=0, velocity_fraction=0.7):
    """Half-widths per source for one run: a dict of (10,) arrays plus the peak |q̈| per joint
    (the motion: each joint within amplitude_rad of CENTRE and velocity_fraction of its limit)."""
    rng = np.random.default_rng(seed)
    motion_kw = dict(centre=CENTRE, position_amplitude_rad=amplitude_rad, velocity_fraction=velocity_fraction)
    t, motion = E.fourier_motion(np.random.default_rng(seed), robot, duration_s, 1000.0, **motion_kw)
    q, v, acc = motion(t)
    tau = E.held_torque(robot, motion, t, theta=theta_true)
    noise = 0.025 * np.abs(tau) + 0.05
    tau_meas = tau + rng.uniform(-1, 1, tau.shape) * noise
    est = _estimator(robot, t, q, v, tau_meas)
    hull, _ = interval_hull(est.rows, est.theta_r, est.theta_r_radius, settings=est.settings)
    peak_torque = np.abs(tau).max(0) / robot.joint_params.torque_limit
    out = {"peak_acc_rad_s2": np.abs(acc).max(0), "peak_torque_ratio": peak_torque.max(), "cond_Y": est.estimate.cond_Y}
    for k, key in SOURCES.items():
        out[f"ls_{k}"] = hull[key]
    out["ls_total"] = sum(out[f"ls_{k}"] for k in SOURCES)
    wide = (np.full(10, -1e3), np.full(10, 1e3))
    out["lp_all"] = _lp_half(est, est.theta_r_radius, wide)
    # Same motion, exact torque, θ_r at nominal: each source alone (the others' radius set to 0).
    nominal = robot.theta.copy()
    nominal[robot.ee_slice] = theta_true[robot.ee_slice]
    clean = _estimator(robot, t, q, v, E.held_torque(robot, motion, t, theta=nominal))
    no_tau = dataclasses.replace(
        clean.rows, r_first=0 * clean.rows.r_first, r_last=0 * clean.rows.r_last, r_inner=0 * clean.rows.r_inner
    )
    zero_r = np.zeros_like(clean.theta_r_radius)
    out["lp_torque"] = _lp_half(clean, zero_r, wide)
    out["lp_theta_r"] = _lp_half(clean, clean.theta_r_radius, wide, no_tau)
    out["lp_quadrature"] = _lp_half(clean, zero_r, wide, no_tau)
    # Prior clipping and physical pruning of the LP box (the truth is in both by assumption).
    full = _lp_bounds(est)
    clipped = (np.maximum(full[0], PRIOR[0]), np.minimum(full[1], PRIOR[1]))
    out["lp_box_half"] = 0.5 * (full[1] - full[0])
    out["prior_clip"] = out["lp_box_half"] - 0.5 * (clipped[1] - clipped[0])
    p_lo, p_hi, ok = prune_box(*clipped, volume=VOLUME, gripper=est.gripper_box)
    out["pruned_half"] = 0.5 * (p_hi - p_lo) if ok else np.full(10, np.nan)
    out["prior_half"] = 0.5 * (PRIOR[1] - PRIOR[0])
    out.update(_update_times(robot, t, q, v, tau_meas))
    return out


def _update_times(robot, t, q, v, tau, repeat=2):
    """Best-of-`repeat` wall time of one estimator update on the whole log: LP over all ten
    parameters, then also with LMI pruning (a fresh estimator each time: no cutting planes kept)."""
    import time

    times = {}
    for key, kw in (("update_all_s", {}), ("update_all_pruned_s", dict(physical_pruning=True, payload_volume=VOLUME))):
        best = np.inf
        for _ in range(repeat):
            est = E.IncrementalEstimator(
                robot,
                settings=E.EstimatorSettings(set_membership="all", **kw),
                prior=PRIOR,
                prior_nominal=PRIOR_NOMINAL,
            )
            est.add(t, q, v, tau)
            start = time.perf_counter()
            est.update()
            best = min(best, time.perf_counter() - start)
        times[key] = best
    return times


def _lp_bounds(est):
    """The LP box of all ten parameters inside the Theorem-2 box (what the estimator publishes
    with set_membership: all, before the prior)."""
    e = est.estimate
    radius = e.radius_torque + e.radius_theta_r + e.radius_quadrature + e.radius_rounding
    lo, hi = e.theta_ls - radius, e.theta_ls + radius
    st = dataclasses.replace(est.settings, set_membership="all")
    s_lo, s_hi, ok = set_membership_bounds(
        est.rows, est.theta_r, est.theta_r_radius, settings=st, box_lo=lo, box_hi=hi, params=range(10)
    )
    return (np.maximum(lo, s_lo), np.minimum(hi, s_hi)) if ok else (lo, hi)


def run(quick: bool = False) -> dict:
    robot = load_robot(coulomb_smoothing=0.01)
    db = load_dumbbells(MODELS_DIR / "dumbbells.yaml")["4lb"]
    theta = E.perturbed_robot_theta(np.random.default_rng(15), robot, 0.05)
    theta[robot.ee_slice] = robot.theta_e + payload_theta_in_end_effector(db, robot.extra["grasp_point"])
    # (amplitude rad, duration s, velocity fraction); the last: at the velocity limit (how far physics allows)
    cases = (
        [(0.6, 3.0, 0.7)]
        if quick
        else [(0.15, 7.5, 0.7), (0.3, 7.5, 0.7), (0.6, 7.5, 0.7), (0.6, 1.5, 0.7), (0.6, 3.0, 0.7), (2.0, 7.5, 1.0)]
    )
    rows = []
    for amp, dur, vf in cases:
        b = budget(robot, theta, amp, dur, velocity_fraction=vf)
        rows.append(
            {
                "amplitude_rad": amp,
                "duration_s": dur,
                "velocity_fraction": vf,
                **{k: np.asarray(v).tolist() for k, v in b.items()},
            }
        )
    return {"payload": "4lb", "names": list(NAMES), "cases": rows}


def print_table(result: dict) -> None:
    names = result["names"]
    keys = [
        ("prior_half", "prior"),
        ("ls_torque", "LS torque"),
        ("ls_theta_r", "LS θ_r ±5%"),
        ("ls_quadrature", "LS quadrature"),
        ("ls_total", "LS total"),
        ("lp_torque", "LP torque only"),
        ("lp_theta_r", "LP θ_r only"),
        ("lp_quadrature", "LP quadrature only"),
        ("lp_all", "LP all sources"),
        ("prior_clip", "prior clipping"),
        ("pruned_half", "LMI-pruned"),
    ]
    for case in result["cases"]:
        acc = " ".join(f"{a:.1f}" for a in case["peak_acc_rad_s2"])
        print(
            f"\namplitude {case['amplitude_rad']} rad, {case['duration_s']} s, "
            f"velocity <= {case['velocity_fraction']} of the limit, peak |q̈| per joint [{acc}] rad/s², "
            f"peak |τ|/limit {case['peak_torque_ratio']:.2f}, "
            f"cond(Y) {case['cond_Y']:.3g}; update {case['update_all_s']:.2f} s (LP all), "
            f"{case['update_all_pruned_s']:.2f} s (+ LMI pruning); half-widths:"
        )
        print(f"| {'source':<20} | " + " | ".join(f"{n:>7}" for n in names) + " |")
        print("|" + "-" * 22 + "|" + "|".join(["-" * 9] * len(names)) + "|")
        for key, label in keys:
            print(f"| {label:<20} | " + " | ".join(f"{x:7.3f}" for x in case[key]) + " |")


def _closed_loop_run(args):
    """One closed-loop run (scenario, overrides, method, seed) -> summary; payloads 4-8 lb by seed."""
    from safesysid.online import run_online
    from safesysid.scenario import SCENARIOS_DIR, load_scenario

    scenario, overrides, method, seed, *vary = args
    scene = load_scenario(SCENARIOS_DIR / scenario, overrides=overrides)
    if not vary or vary[0]:  # payloads 4-8 lb by seed; else the scenario's own payload
        payload = ["4lb", "5lb", "6lb", "7lb", "8lb"][seed % 5]
        scene = dataclasses.replace(scene, payload=dataclasses.replace(scene.payload, dumbbell=payload))
    return run_online(scene, None, method=method, seed=seed, write=False)


SAFETY_RATIOS = (
    "max_commanded_torque_ratio",
    "max_joint_limit_ratio",
    "max_velocity_ratio",
    "max_tracking_error_ratio",
)


def closed_loop(
    seeds, scenario="identify_all.yaml", methods=("ours", "random"), workers=1, overrides=(), *, vary_payload=True
) -> dict:
    """Width / prior width per parameter over closed-loop runs of a scenario (payloads 4-8 lb by
    seed, or the scenario's own with vary_payload False; overrides: scenario layers, as
    --scenario-text), medians of the published, data-driven (before pruning) and the paper's
    first-order interval; the published and data-driven ratios and cond(Y) of every run."""
    from concurrent.futures import ProcessPoolExecutor

    jobs = [(scenario, list(overrides), method, seed, vary_payload) for method in methods for seed in seeds]
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            summaries = list(pool.map(_closed_loop_run, jobs))
    else:
        summaries = [_closed_loop_run(job) for job in jobs]
    width = lambda s, key: np.array(s["estimate"][f"{key}upper"]) - np.array(s["estimate"][f"{key}lower"])  # noqa: E731
    prior = PRIOR[1] - PRIOR[0]
    out = {}
    for method in methods:
        runs = [s for job, s in zip(jobs, summaries) if job[2] == method]
        out[method] = {
            "contains": [bool(s["contains_truth"]) for s in runs],
            "consistent": [bool(s["estimate"]["consistent"]) for s in runs],
            "mass_half_width_kg": [float(width(s, "")[0] / 2) for s in runs],
            "cond_Y": [float(s["cond_Y"]) for s in runs],
            "data_ratios": [(width(s, "data_") / prior).tolist() for s in runs],
            "published_ratios": [(width(s, "") / prior).tolist() for s in runs],
            "safety": {  # the referee's measures over the runs (worst case)
                "success": sum(bool(s["success"]) for s in runs),
                "collisions": sum(int(s["collisions"]) for s in runs),
                "min_clearance_m": min(float(s["min_clearance_m"]) for s in runs),
                **{key: max(float(s[key]) for s in runs) for key in SAFETY_RATIOS},
            },
            "solve_time_s": [t for s in runs for t in s["planner"]["solve_time_s"]],
            **{
                f"{key or 'published_'}ratio": np.median([width(s, key) / prior for s in runs], 0).tolist()
                for key in ("", "data_", "first_order_")
            },
        }
    return out


def print_width_ratios(ours: np.ndarray, rand: np.ndarray) -> None:
    """The restated identification target on paired runs' published widths (table_iv's measure)."""
    from safesysid.table_iv import width_ratio_summary

    r = width_ratio_summary(ours, rand)
    below = sum(x < 1 for x in r["median"])
    print(f"published width ours / random, median over pairs: {np.round(r['median'], 3).tolist()} ({below}/10 < 1)")
    print(f"published width, fraction of pairs ours narrower: {np.round(r['won'], 2).tolist()}")


def print_closed_loop(result: dict) -> None:
    print(f"| {'median width / prior':<26} | " + " | ".join(f"{n:>6}" for n in NAMES) + " |")
    print("|" + "-" * 28 + "|" + "|".join(["-" * 8] * len(NAMES)) + "|")
    for method, r in result.items():
        for key, label in (
            ("published_ratio", "pruned"),
            ("data_ratio", "data-driven"),
            ("first_order_ratio", "paper first-order"),
        ):
            print(f"| {method + ' ' + label:<26} | " + " | ".join(f"{x:6.3f}" for x in r[key]) + " |")
        worst = np.max(r["data_ratios"], 0)
        print(f"| {method + ' data-driven, max':<26} | " + " | ".join(f"{x:6.3f}" for x in worst) + " |")
    for method, r in result.items():
        print(
            f"{method}: contains {sum(r['contains'])}/{len(r['contains'])}, consistent {sum(r['consistent'])}, "
            f"median cond(Y) {np.median(r['cond_Y']):.1f}, "
            f"mass half-width kg {[round(x, 3) for x in r['mass_half_width_kg']]}"
        )
        times = np.array(r["solve_time_s"])
        print(
            f"  safety {json.dumps({k: round(v, 3) for k, v in r['safety'].items()})}; planning call median "
            f"{np.median(times):.2f} s, max {times.max():.2f} s (simulated; the iteration budget)"
        )
    if {"ours", "random"} <= result.keys():  # paired seeds: where ours' data-driven box is narrower
        ours, rand = (np.array(result[m]["data_ratios"]) for m in ("ours", "random"))
        narrower = ours < rand
        wins = narrower.sum(1)
        print(f"ours narrower than random, pairs per parameter: {narrower.sum(0).tolist()} of {len(wins)}")
        print(
            f"parameters where ours is narrower, per pair: {wins.tolist()}; pairs with >= 8: {int(np.sum(wins >= 8))}"
        )
        print(f"data-driven width ours / random, median over pairs: {np.round(np.median(ours / rand, 0), 2).tolist()}")
        if all("published_ratios" in result[m] for m in ("ours", "random")):  # saved files before it lack it
            published = (np.array(result[m]["published_ratios"]) for m in ("ours", "random"))
            print_width_ratios(*published)
        # The mass's width does not move with the motion (the budget above): were it won or lost in every pair.
        others = narrower[:, 1:].sum(1)
        print(f"pairs with >= 8 were m won in every pair: {int(np.sum(others >= 7))}, lost: {int(np.sum(others >= 8))}")
        ours, rand = (np.array(result[m]["cond_Y"]) for m in ("ours", "random"))
        ratio = np.median(ours) / np.median(rand)
        print(f"cond(Y) ours lower in {int(np.sum(ours < rand))}/{len(wins)}, medians ratio {ratio:.2f}")


if __name__ == "__main__":
    if "--closed-loop" in sys.argv:  # --closed-loop N [--workers W] [--scenario-text T]: identify_all seeds 0..N-1
        arg = lambda flag: sys.argv[sys.argv.index(flag) + 1] if flag in sys.argv else None  # noqa: E731
        # --first-seed S: seeds S..S+N-1; --scenario NAME (of scenarios/); --same-payload: its own payload
        first = int(arg("--first-seed") or 0)
        seeds = list(range(first, first + int(arg("--closed-loop"))))
        overrides = [arg("--scenario-text")] if arg("--scenario-text") else []
        methods = tuple((arg("--methods") or "ours,random").split(","))
        result = closed_loop(
            seeds,
            scenario=arg("--scenario") or "identify_all.yaml",
            methods=methods,
            workers=int(arg("--workers") or 1),
            overrides=overrides,
            vary_payload="--same-payload" not in sys.argv,
        )
        if arg("--save"):
            with open(arg("--save"), "w") as f:
                json.dump({"seeds": seeds, "overrides": overrides, "result": result}, f)
        if arg("--paired-with"):
            with open(arg("--paired-with")) as f:
                saved = json.load(f)
            if saved["seeds"] != seeds:
                sys.exit(f"{arg('--paired-with')}: seeds {saved['seeds']} differ from this run's {seeds}")
            result = {**{m: r for m, r in saved["result"].items() if m not in result}, **result}
        print_closed_loop(result)
    else:
        print_table(run(quick="--quick" in sys.argv))
