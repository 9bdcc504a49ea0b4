"""A5 and the acceleration bound of its certificate, measured (docs/guarantees.md §5 "A5 certified
from an acceleration bound", "Known limits").

    python experiments/a5_acceleration.py RUN_DIR

RUN_DIR: a `safesysid run scenarios/quickstart.yaml --out RUN_DIR` output. Prints
1. the peak mean acceleration |Δq̇|/h per joint of its log.csv (what a declared bound must exceed);
2. the a priori bound from the dynamics under the logged torque, |q̈|₂ ≤ ‖|τ_meas − h(q, q̇; θ_c)| +
   torque radius + rad h(q, q̇; [θ])‖₂ / λ_min(M) at every 250th logged state (h by the planner's interval passivity
   regressor at the point state over the Table II prior and the A1 box, λ_min(M) certified as the
   controller's `mass_matrix_lower_bound`), even before widening the state over a step;
3. for a 1 s smooth Fourier motion with a per-step bound as tight as the motion (10 % over its dense
   peak on each step): the certificate over A5's value per step (median) and the share of steps
   where A5's value is at least the certificate (where the check shows A5).
"""

import sys
from pathlib import Path

import numpy as np
from safesysid.systems import estimation as E
from safesysid.systems.controller.armour import mass_matrix_lower_bound
from safesysid.systems.estimation import quadrature_certificate as qc
from safesysid.systems.estimation import segments as sg
from safesysid.systems.math.intervals import Interval
from safesysid.systems.model.robot_model import load_robot
from safesysid.systems.model.torque_noise import DeclaredTorqueNoise
from safesysid.systems.model.uncertainty import parameter_radius
from safesysid.systems.planner.interval_dynamics import interval_passivity_regressor

PRIOR = (np.array([1.2, -0.4, -0.4, -1.0] + [-0.2] * 6), np.array([5.2, 0.4, 0.4, -0.1] + [0.2] * 6))
CENTRE = [0.0, 0.3, 0.0, 1.5, 0.0, 0.8, 0.0]


def theta_box(robot):
    radius = parameter_radius(robot, 0.05, 0.05)
    centre = robot.theta.copy()
    centre[robot.ee_slice], radius[robot.ee_slice] = 0.5 * (PRIOR[0] + PRIOR[1]), 0.5 * (PRIOR[1] - PRIOR[0])
    return centre, radius


def logged(run_dir, robot):
    d = np.loadtxt(Path(run_dir) / "log.csv", delimiter=",", skiprows=1)
    n = robot.n
    return d[:, 0], d[:, 1 : 1 + n], d[:, 1 + n : 1 + 2 * n], d[:, 1 + 2 * n : 1 + 3 * n]


def dynamics_bound(robot, q, v, tau):
    centre, radius = theta_box(robot)
    sigma = mass_matrix_lower_bound(robot.n, centre - radius)
    box = lambda x: Interval(x, x)  # noqa: E731
    w = interval_passivity_regressor(robot, box(q), box(v), box(v), box(0 * v))
    # |u − h(θ_true)| ≤ |τ_meas − W_mid θ_c| + r + W_rad |θ_c| + |W| θ_rad (u within r of τ_meas, A3)
    spread = w.rad @ np.abs(centre) + w.mag @ radius
    r = DeclaredTorqueNoise().bound_from_measured(tau, None)
    return np.linalg.norm(np.abs(tau - w.mid @ centre) + r + spread, axis=1) / sigma, sigma


def tightness(robot):
    t, motion = E.fourier_motion(np.random.default_rng(5), robot, 1.0, 1000.0, centre=CENTRE)
    q, v, _ = motion(t)
    h = np.diff(t)
    dense = t[:-1, None] + h[:, None] * np.linspace(0, 1, 33)[None, :]
    accel = 1.1 * np.abs(motion(dense.ravel())[2]).reshape(len(h), 33, -1).max(1) + 1e-6
    box = theta_box(robot)
    cert, _ = qc.certified_step_bounds(robot, t, q, v, accel, box, integration="trapezoid")
    fric = sg.regressors.friction_columns(v, kind="rate", smoothing_velocity=robot.coulomb_smoothing)
    rates = sg.integrand_rates(t, sg._pair_factors(robot.tree, q, v), fric, *box)
    a5 = 0.25 * 2.0 * h[:, None] ** 2 * sg.neighbour_max(rates)
    return np.median(cert / np.maximum(a5, 1e-300)), np.mean(cert <= a5)


def main(run_dir):
    robot = load_robot(coulomb_smoothing=0.01)
    t, q, v, tau = logged(run_dir, robot)
    mean_acc = np.abs(np.diff(v, axis=0)) / np.diff(t)[:, None]
    print("1. peak mean acceleration per joint (rad/s²):", np.round(mean_acc.max(0), 3).tolist())
    pick = slice(0, len(t), 250)
    bound, sigma = dynamics_bound(robot, q[pick], v[pick], tau[pick])
    print(
        f"2. a priori dynamics bound (rad/s², λ_min(M) ≥ {sigma:.3g}): min {bound.min():.1f}, median "
        f"{np.median(bound):.1f}; {np.median(bound) / mean_acc.max():.0f}× the peak mean acceleration"
    )
    ratio, share = tightness(robot)
    print(
        f"3. per-step tight bound, smooth motion: certificate / A5 median {ratio:.2f}, "
        f"A5 shown on {share:.1%} of the steps"
    )


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
