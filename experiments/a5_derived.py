"""The acceleration bound derived online (estimation/acceleration_bound.py), measured on a run's log
(docs/guarantees.md §5 "A5 certified from the dynamics").

    python experiments/a5_derived.py RUN_DIR

RUN_DIR: a `safesysid run scenarios/quickstart.yaml --out RUN_DIR` output. For every step of its
log.csv (t, q, q̇, the measured torque held over the step), the bound derived with the declared
torque noise and [θ] = θ_r ± 5 % with [θ_e] the box published at that step (the log's est_*_lo/hi,
the Table II prior before the first update), as the estimator derives it: per joint its median and
largest value, the step's own mean acceleration |Δq̇|/h over it (at most 1 on every step: the
samples never contradict it), the bound's median over the run's peak mean acceleration, and the
cost per step (ms).
"""

import sys
import time

import numpy as np
from a5_acceleration import PRIOR, logged
from safesysid.systems.estimation.acceleration_bound import derived_acceleration_bound
from safesysid.systems.model.robot_model import load_robot
from safesysid.systems.model.torque_noise import DeclaredTorqueNoise
from safesysid.systems.model.uncertainty import parameter_radius


def published_boxes(run_dir, n_rows):
    """(lower, upper) (N, 10) of θ_e published at each logged step (the prior where none was yet)."""
    names = open(f"{run_dir}/log.csv").readline().strip().split(",")
    d = np.loadtxt(f"{run_dir}/log.csv", delimiter=",", skiprows=1)
    lo_cols = [i for i, x in enumerate(names) if x.startswith("est_") and x.endswith("_lo")]
    hi_cols = [i for i, x in enumerate(names) if x.startswith("est_") and x.endswith("_hi")]
    lo, hi = d[:n_rows, lo_cols], d[:n_rows, hi_cols]
    prior = ~(np.all(np.isfinite(lo), 1) & np.all(np.isfinite(hi), 1))
    lo[prior], hi[prior] = PRIOR[0], PRIOR[1]
    return lo, hi


def derived(robot, t, q, v, tau, boxes, chunk=100):
    """Per step (N − 1, n), chunk by chunk with the box published at the chunk's start."""
    radius = DeclaredTorqueNoise().bound_from_measured(tau, None)
    centre, rad = robot.theta.copy(), parameter_radius(robot, 0.05, 0.05)
    ee, out = robot.ee_slice, []
    for a in range(0, len(t) - 1, chunk):
        b = min(a + chunk, len(t) - 1)
        c, r = centre.copy(), rad.copy()
        c[ee], r[ee] = 0.5 * (boxes[0][a] + boxes[1][a]), 0.5 * (boxes[1][a] - boxes[0][a])
        s = slice(a, b + 1)
        out.append(derived_acceleration_bound(robot, (t[s], q[s], v[s], tau[s]), radius[s], (c, r)))
    return np.concatenate(out)


def main(run_dir):
    robot = load_robot(coulomb_smoothing=0.01)
    t, q, v, tau = logged(run_dir, robot)
    mean_acc = np.abs(np.diff(v, axis=0)) / np.diff(t)[:, None]
    start = time.perf_counter()
    bound = derived(robot, t, q, v, tau, published_boxes(run_dir, len(t)))
    cost = (time.perf_counter() - start) / len(bound) * 1e3
    print("peak mean acceleration per joint (rad/s²):", np.round(mean_acc.max(0), 3).tolist())
    print("derived bound, median per joint (rad/s²):", np.round(np.median(bound, 0), 2).tolist())
    print("derived bound, largest per joint (rad/s²):", np.round(bound.max(0), 2).tolist())
    print(f"unbounded steps: {int(np.sum(~np.isfinite(bound).all(1)))} of {len(bound)}")
    print(f"largest |Δq̇|/h over the bound on its step: {np.max(mean_acc / bound):.3f}")
    print(f"median bound over the run's peak mean acceleration: {np.median(bound) / mean_acc.max():.1f}×")
    print(f"cost: {cost:.2f} ms per step")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
