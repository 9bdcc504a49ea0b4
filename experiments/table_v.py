"""Paper Table V: Pearson correlation between cond(W) and cond(Y) over random Fourier trajectories.

For each random 10 s trajectory sampled at 1 kHz: W = the end-effector columns of the standard
regressor stacked over all samples; Y_h = the momentum observation matrix (end-effector
columns) with segments of h samples (trapezoid integral of Wc). Then, for each h, the Pearson
correlation across trajectories of cond(W) and cond(Y_h).

    python experiments/table_v.py [--trajectories 60] [--seed 0] [--out table_v.md]
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from safesysid.systems import estimation as est_mod
from safesysid.systems.model import regressors
from safesysid.systems.model.robot_model import load_robot

HORIZONS = (1, 5, 10, 20, 50, 100, 200, 500)
PAPER = {1: 1.0000, 5: 1.0000, 10: 0.9994, 20: 0.9934, 50: 0.9540, 100: 0.6709, 200: 0.3537, 500: 0.2789}
CENTRE = [0.0, 0.3, 0.0, 1.5, 0.0, 0.8, 0.0]
PERIOD_S = 1.0  # Fourier base period; 5 harmonics up to 5 Hz (the paper does not give its band)
HARMONICS = 5


def observation_matrix(wm_e, wc_e, dt, h):
    """Y_h (rows of n per segment) from per-sample Wm_e, Wc_e on a uniform grid, h samples/segment."""
    nseg = (len(wm_e) - 1) // h
    starts = np.arange(nseg) * h
    trap = 0.5 * dt * (wc_e[:-1] + wc_e[1:])  # step integrals
    cum = np.concatenate([np.zeros((1,) + trap.shape[1:]), np.cumsum(trap, 0)])
    y = wm_e[starts + h] - wm_e[starts] - (cum[starts + h] - cum[starts])
    return y.reshape(-1, wm_e.shape[-1])


def conditions(robot, rng, duration_s=10.0, rate_hz=1000.0, period_s=PERIOD_S, harmonics=HARMONICS):
    t, q, v, a = est_mod.fourier_trajectory(
        rng, robot, duration_s, rate_hz=rate_hz, harmonics=harmonics, period_s=period_s, centre=CENTRE
    )
    ee = [robot.end_effector]
    tree = robot.tree
    w = regressors.standard_regressor(tree, q, v, a, bodies=ee).reshape(-1, 10)
    wm = regressors.momentum_regressor(tree, q, v, bodies=ee)
    wc = regressors.momentum_rate_regressor(tree, q, v, bodies=ee)
    cond_w = np.linalg.cond(w)
    cond_y = {h: np.linalg.cond(observation_matrix(wm, wc, 1.0 / rate_hz, h)) for h in HORIZONS}
    return cond_w, cond_y


def table(trajectories=60, seed=0, period_s=PERIOD_S, harmonics=HARMONICS):
    robot = load_robot()
    rng = np.random.default_rng(seed)
    cw, cy = [], {h: [] for h in HORIZONS}
    for _ in range(trajectories):
        w, y = conditions(robot, rng, period_s=period_s, harmonics=harmonics)
        cw.append(w)
        for h in HORIZONS:
            cy[h].append(y[h])
    cw = np.array(cw)
    return {
        h: {"pearson": float(np.corrcoef(cw, cy[h])[0, 1]), "median_cond_Y": float(np.median(cy[h]))} for h in HORIZONS
    }, float(np.median(cw))


def markdown(result, median_cond_w, trajectories, period_s=PERIOD_S, harmonics=HARMONICS):
    lines = [
        f"Pearson correlation of cond(W) and cond(Y) over {trajectories} random Fourier trajectories "
        f"(10 s at 1 kHz, base period {period_s:g} s, {harmonics} harmonics, Kinova Gen3 end effector; "
        f"median cond(W) = {median_cond_w:.4g})",
        "",
        "| h (samples) | h (s) | Pearson (ours) | Pearson (paper) | median cond(Y) |",
        "|---|---|---|---|---|",
    ]
    for h, row in result.items():
        lines.append(f"| {h} | {h / 1000:.3f} | {row['pearson']:.4f} | {PAPER[h]:.4f} | {row['median_cond_Y']:.4g} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--period", type=float, default=PERIOD_S, help="Fourier base period [s]")
    parser.add_argument("--harmonics", type=int, default=HARMONICS)
    parser.add_argument("--out", help="also write the markdown table here")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    result, cw = table(args.trajectories, args.seed, args.period, args.harmonics)
    text = markdown(result, cw, args.trajectories, args.period, args.harmonics)
    print(text)
    print(f"({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
