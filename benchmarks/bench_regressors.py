"""Regressor time per sample: ours (numpy, vectorized) vs Drake AutoDiffXd vs Pinocchio.

Drake has no regressor API; its AutoDiffXd inverse dynamics with the 10 end-effector
parameters as derivative directions gives W_e one sample at a time. Pinocchio's
computeJointTorqueRegressor (if `pin` is installed) gives the full standard regressor.
Target: >= 20x faster than AutoDiffXd and within 2x of Pinocchio per sample.
"""

from __future__ import annotations

import time

import numpy as np
from safesysid.benchmarks.scaling import load_average, plot, png
from safesysid.systems.controller.armour_fast import FastControllerDynamics
from safesysid.systems.model import regressors
from safesysid.systems.model.robot_model import load_robot, make_plant


def _per_sample(fn, count, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best / count


def drake_autodiff_setup(robot):
    """(plant, context, forces): Drake's AutoDiffXd plant with the 10 end-effector parameters as
    the derivative directions (built once; not part of the per-sample cost)."""
    from pydrake.autodiffutils import InitializeAutoDiff
    from pydrake.multibody.tree import MultibodyForces_, SpatialInertia_, UnitInertia_

    plant, _, _ = make_plant(robot.source)
    plant.Finalize()
    ad = plant.ToAutoDiffXd()
    ctx = ad.CreateDefaultContext()
    body = ad.GetBodyByName(robot.body_names[robot.end_effector])
    theta_ad = InitializeAutoDiff(robot.theta_e)[:, 0]
    m = theta_ad[0]
    com = theta_ad[1:4] / m
    i = theta_ad[4:]
    unit = UnitInertia_[type(m)](i[0] / m, i[1] / m, i[2] / m, i[3] / m, i[5] / m, i[4] / m)
    body.SetSpatialInertiaInBodyFrame(ctx, SpatialInertia_[type(m)](m, com, unit, skip_validity_check=True))
    return ad, ctx, MultibodyForces_[type(m)](ad)


def drake_autodiff_we(robot, q, v, a, setup=None):
    """W_e rows for each sample from Drake's AutoDiffXd inverse dynamics."""
    from pydrake.autodiffutils import ExtractGradient

    ad, ctx, forces = setup or drake_autodiff_setup(robot)
    out = []
    for k in range(len(q)):
        ad.SetPositions(ctx, q[k].astype(object) * 1.0)
        ad.SetVelocities(ctx, v[k].astype(object) * 1.0)
        ad.CalcForceElementsContribution(ctx, forces)
        tau = ad.CalcInverseDynamics(ctx, a[k], forces)
        out.append(ExtractGradient(tau))
    return np.array(out)


def pinocchio_model(robot):
    """Pinocchio model of our URDF (visuals stripped: urdfdom does not know Drake's capsule)."""
    import re
    import tempfile

    import pinocchio as pin

    text = re.sub(r"<visual>.*?</visual>", "", open(robot.source).read(), flags=re.S)
    with tempfile.NamedTemporaryFile("w", suffix=".urdf", delete=False) as fh:
        fh.write(text)
    return pin.buildModelFromUrdf(fh.name)


def pinocchio_configuration(model, q):
    """Our joint angles -> Pinocchio q (continuous joints are stored as cos, sin)."""
    out = np.zeros((len(q), model.nq))
    for k, joint in enumerate(model.joints[1:]):
        if joint.nq == 2:
            out[:, joint.idx_q], out[:, joint.idx_q + 1] = np.cos(q[:, k]), np.sin(q[:, k])
        else:
            out[:, joint.idx_q] = q[:, k]
    return out


def pinocchio_regressor(model, q, v, a):
    import pinocchio as pin

    data = model.createData()
    qp = pinocchio_configuration(model, q)
    return np.array([pin.computeJointTorqueRegressor(model, data, qp[k], v[k], a[k]).copy() for k in range(len(q))])


BATCHES = (1, 10, 100, 1000, 10000)


def _batch_row(robot, model, setup, q, v, a, n_ad):
    """µs per sample at one batch size (small batches repeated so the clock resolves them)."""
    tree, ee, b = robot.tree, [robot.end_effector], len(q)
    count = max(1, min(1000 // b, 100))

    def ours(**kw):
        return 1e6 * _per_sample(
            lambda: [regressors.standard_regressor(tree, q, v, a, **kw) for _ in range(count)], b * count
        )

    row = {"ours_We_us": ours(bodies=ee), "ours_W_full_us": ours()}
    # The controller's one-sample path (Wp and Wm of all 14 n parameters at once, armour_fast).
    dyn, m = FastControllerDynamics(robot), min(b, 100)
    row["ours_controller_Wp_Wm_us"] = 1e6 * _per_sample(
        lambda: [dyn.regressors(q[k], v[k], v[k], aa=a[k], x=v[k]) for k in range(m)], m
    )
    ad = lambda: drake_autodiff_we(robot, q[:n_ad], v[:n_ad], a[:n_ad], setup)  # noqa: E731
    row["drake_autodiff_We_us"] = 1e6 * _per_sample(ad, n_ad, repeat=1)
    if model is not None:
        n_pin = min(b, 2000)
        pin = lambda: pinocchio_regressor(model, q[:n_pin], v[:n_pin], a[:n_pin])  # noqa: E731
        row["pinocchio_W_full_us"] = 1e6 * _per_sample(pin, n_pin)
    return row


def scaling(quick: bool = False, out=None) -> dict:
    """Time per sample vs batch size in one run: ours (W_e and the full W, vectorized over the
    batch; the controller's one-sample Wp + Wm, looped), Drake AutoDiffXd (W_e, one sample at a
    time, at most 300 timed) and Pinocchio when installed; the looped ones do not depend on the
    batch beyond noise."""
    robot = load_robot()
    batches = BATCHES[:3] if quick else BATCHES
    rng = np.random.default_rng(1)
    setup = drake_autodiff_setup(robot)
    try:
        import pinocchio  # noqa: F401

        model = pinocchio_model(robot)
    except ImportError:
        model = None
    rows = {}
    for b in batches:
        q, v, a = rng.uniform(-2, 2, size=(3, b, robot.n))
        rows[str(b)] = _batch_row(robot, model, setup, q, v, a, min(b, 30 if quick else 300))
    series = {k: [r.get(k, np.nan) for r in rows.values()] for k in rows[str(batches[0])]}
    return {
        "vs_batch": rows,
        "pinocchio": "measured" if model is not None else "not installed (pip install -e '.[bench]'): column skipped",
        "load_average": load_average(),
        "plot": plot(
            png(out, "regressors_vs_batch"),
            list(batches),
            series,
            "batch size",
            "µs per sample",
            "regressor time per sample vs batch",
            logx=True,
            logy=True,
        ),
    }


def run(quick=False, out=None):
    robot = load_robot()
    n_samples = 1000 if quick else 10000
    rng = np.random.default_rng(0)
    q, v, a = rng.uniform(-2, 2, size=(3, n_samples, robot.n))
    ee = [robot.end_effector]
    tree = robot.tree
    result = {"samples": n_samples}
    result["ours_We_us"] = 1e6 * _per_sample(lambda: regressors.standard_regressor(tree, q, v, a, bodies=ee), n_samples)
    result["ours_Wme_us"] = 1e6 * _per_sample(lambda: regressors.momentum_regressor(tree, q, v, bodies=ee), n_samples)
    result["ours_Wce_us"] = 1e6 * _per_sample(
        lambda: regressors.momentum_rate_regressor(tree, q, v, bodies=ee), n_samples
    )
    result["ours_W_full_us"] = 1e6 * _per_sample(lambda: regressors.standard_regressor(tree, q, v, a), n_samples)
    n_ad = min(n_samples, 300)
    w_ad = drake_autodiff_we(robot, q[:n_ad], v[:n_ad], a[:n_ad])
    w_ours = regressors.standard_regressor(tree, q[:n_ad], v[:n_ad], a[:n_ad], bodies=ee)
    # AutoDiff derivative w.r.t. theta_e through the (m, com, unit inertia) construction is the regressor.
    result["autodiff_max_abs_diff"] = float(np.abs(w_ad - w_ours).max())
    result["drake_autodiff_We_us"] = 1e6 * _per_sample(
        lambda: drake_autodiff_we(robot, q[:n_ad], v[:n_ad], a[:n_ad]), n_ad, repeat=1
    )
    result["speedup_vs_autodiff"] = result["drake_autodiff_We_us"] / result["ours_We_us"]
    try:
        import pinocchio  # noqa: F401
    except ImportError:
        result["pinocchio"] = "not installed (pip install -e '.[bench]')"
    else:
        n_pin = min(n_samples, 2000)
        model = pinocchio_model(robot)
        w_pin = pinocchio_regressor(model, q[:50], v[:50], a[:50])
        # Pinocchio's per-body order is [m, mc, Ixx, Ixy, Iyy, Ixz, Iyz, Izz].
        theta_pin = robot.theta[: 10 * robot.n].reshape(-1, 10)[:, [0, 1, 2, 3, 4, 7, 5, 9, 8, 6]].ravel()
        result["pinocchio_tau_max_abs_diff"] = float(
            np.abs(
                w_pin @ theta_pin
                - regressors.standard_regressor(tree, q[:50], v[:50], a[:50]) @ robot.theta[: 10 * robot.n]
            ).max()
        )
        result["pinocchio_W_full_us"] = 1e6 * _per_sample(
            lambda: pinocchio_regressor(model, q[:n_pin], v[:n_pin], a[:n_pin]), n_pin
        )
        result["ours_over_pinocchio_full"] = result["ours_W_full_us"] / result["pinocchio_W_full_us"]
        result["ours_We_over_pinocchio_full"] = result["ours_We_us"] / result["pinocchio_W_full_us"]
    result["scaling"] = scaling(quick, out)
    return result


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
