"""Helpers shared by the tests (imported as `from helpers import ...`; fixtures live in conftest.py)."""

import os
from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"
FULL = os.environ.get("SAFESYSID_FULL") == "1"

# Identification runs: the arm's centre pose and the paper's payloads.
CENTRE = [0.0, 0.3, 0.0, 1.5, 0.0, 0.8, 0.0]
PAYLOADS = ["4lb", "5lb", "6lb", "7lb", "8lb"]
# The paper's Table II prior of the end effector + payload (box, nominal).
PRIOR = (np.array([1.2, -0.4, -0.4, -1.0] + [-0.2] * 6), np.array([5.2, 0.4, 0.4, -0.1] + [0.2] * 6))
PRIOR_NOMINAL = np.array([3.2, 0.0, 0.0, -0.5] + [0.0] * 6)


SCHEMAS = Path(__file__).resolve().parents[1] / "docs" / "schemas"
SCHEMA_OF = {"summary.json": "summary", "diagnosis.json": "diagnosis", "aggregate.json": "aggregate"}
# A key every output of the program has: hand-written stand-ins in tests (a partial summary fed to
# a reader) are not outputs and are not judged.
WRITTEN_BY_THE_PROGRAM = {"summary": "sim_time_s", "diagnosis": "gap", "aggregate": "trials"}


def validate_outputs(folder: Path) -> int:
    """Validate every summary.json, diagnosis.json and aggregate.json under folder against
    docs/schemas (a no-op without jsonschema); returns how many files were checked."""
    try:
        import jsonschema
    except ImportError:
        return 0
    import json

    checked = 0
    for name, schema in SCHEMA_OF.items():
        for path in Path(folder).rglob(name):
            output = json.loads(path.read_text())
            if WRITTEN_BY_THE_PROGRAM[schema] not in output:
                continue
            doc = json.loads((SCHEMAS / f"{schema}.schema.json").read_text())
            try:
                jsonschema.validate(output, doc)
            except jsonschema.ValidationError as err:
                raise AssertionError(f"{path} does not match docs/schemas/{schema}.schema.json: {err.message}") from err
            checked += 1
    return checked


def leaves(system):
    """Every leaf system of a Drake diagram (or the system itself)."""
    from pydrake.systems.framework import Diagram

    if isinstance(system, Diagram):
        for sub in system.GetSystems():
            yield from leaves(sub)
    else:
        yield system


def n_trials(small, full):
    """Monte-Carlo sample size: small in CI, full with SAFESYSID_FULL=1."""
    return full if FULL else small


def shared_path(*parts):
    """A file under ../shared, or skip the test when the shared data is absent."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data not available: {path}")
    return path


def params_with_spheres(tmp_path, spheres_path):
    """A copy of the Gen3 parameter file whose planner_spheres is `spheres_path` (same URDF)."""
    from safesysid.systems.model.robot_model import MODELS_DIR

    params = tmp_path / "params.yaml"
    params.write_text(
        (MODELS_DIR / "kinova_gen3_params.yaml")
        .read_text()
        .replace("urdf: kinova_gen3.urdf", f"urdf: {MODELS_DIR / 'kinova_gen3.urdf'}")
        .replace("planner_spheres: kinova_gen3_spheres.yaml", f"planner_spheres: {spheres_path}")
    )
    return params


def simulate_online(built, scenario, duration_s):
    """Simulate an online diagram (app/online.py build_online) from rest at q0 for duration_s;
    returns the root context."""
    from pydrake.systems.analysis import Simulator

    sim = Simulator(built.diagram)
    ctx = sim.get_mutable_context()
    built.arm.seed_noise(ctx)
    built.arm.set_state(ctx, np.asarray(scenario.q0_rad, float))
    sim.Initialize()
    sim.AdvanceTo(duration_s)
    return ctx


def event_kinds(summary: dict) -> list[str]:
    return [e["kind"] for e in summary.get("events", [])]


def assert_safe(summary: dict, *, complete: bool = True) -> None:
    """The referee's verdict on a run summary, every guarantee on its own line so a failure names
    it. complete: the run also stayed in its tube, contains the truth and succeeded; without it
    (a run with injected faults) the estimator need only be honest: consistent => contains the
    truth, inconsistent => an `inconsistent_estimate` event."""
    assert summary["collisions"] == 0 and summary["min_clearance_m"] >= 0.0, "collision"
    assert summary["max_commanded_torque_ratio"] <= 1.0 + 1e-9, "torque limit (command before saturation)"
    assert summary["max_joint_limit_ratio"] <= 1.0, "joint limit"
    assert summary["max_velocity_ratio"] <= 1.0, "velocity limit"
    if complete:
        assert summary["max_tracking_error_ratio"] <= 1.0 + 1e-9, "tracking tube"
        assert summary["contains_truth"], "containment"
        assert summary["success"] and summary["failure"] is None
    elif summary["estimate"]["consistent"]:
        assert summary["contains_truth"], "a consistent interval excludes the truth"
    else:
        assert "inconsistent_estimate" in event_kinds(summary)


def mass_matrices(robot, q, theta):
    """(N, n, n) robot.mass_matrix at each row of q (N, n) with its own theta (N, p), or one theta
    (p,) for all: the same momentum-regressor columns, but every row and unit velocity in one batch
    (robot.mass_matrix makes n regressor calls per q: the tests' per-state truths were most of
    their run time). tests/test_reachability.py checks it against robot.mass_matrix."""
    q = np.atleast_2d(q)
    count, n = q.shape
    theta = np.broadcast_to(theta, (count, np.shape(theta)[-1]))
    eye = np.tile(np.eye(n), (count, 1))
    wm = robot.momentum_regressor(np.repeat(q, n, axis=0), eye).reshape(count, n, n, -1)  # (row, column k, i, p)
    return np.einsum("rkip,rp->rik", wm, theta)


GAUSS = np.polynomial.legendre.leggauss(24)  # per step: exact enough for one oscillation period


def held_torque(robot, motion, t, theta, *, h):
    """τ̄_k = (1/h)∫τ_ID dt over each step of length h (24-point Gauss): the held torque that
    produces the motion, so ∫τ is exact and only the quadrature errs."""
    nodes = t[:, None] + 0.5 * h * (1 + GAUSS[0][None, :])
    q, v, a = motion(nodes.ravel())
    tau = robot.inverse_dynamics(q, v, a, theta=theta).reshape(len(t), len(GAUSS[0]), -1)
    return 0.5 * np.tensordot(tau, GAUSS[1], axes=([1], [0]))


def start_arm_sim(tmp_path, scenario, scenario_text, *, duration_s):
    """`safesysid arm-sim` in a process of its own (normal priority), once it answers: (process, out dir)."""
    import os
    import subprocess
    import sys
    import time

    out = tmp_path / "arm"
    args = ["arm-sim", str(scenario), "--out", str(out), "--duration", str(duration_s), "--no-fifo"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "safesysid.cli", *args, "--scenario-text", scenario_text],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env=dict(os.environ, PYTHONFAULTHANDLER="1"),  # a crash prints its stack into the output
    )
    deadline = time.monotonic() + 120
    while not (out / "ready").exists():
        assert proc.poll() is None, proc.stdout.read().decode()
        assert time.monotonic() < deadline, "arm-sim did not start"
        time.sleep(0.2)
    return proc, out
