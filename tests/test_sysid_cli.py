"""`safesysid sysid LOG.csv --scenario S.yaml --out DIR` end to end, and its bad-input errors."""
import json

import numpy as np
import pytest

from safesysid.cli import main
from safesysid.joint_log import JointLog, write_joint_log
from safesysid.systems import estimation as E
from safesysid.systems.payload import load_dumbbells, payload_theta_in_end_effector
from safesysid.systems.robot_model import MODELS_DIR, load_robot

CENTRE = [0.0, 0.3, 0.0, 1.5, 0.0, 0.8, 0.0]


@pytest.fixture(scope="module")
def robot():
    return load_robot(coulomb_smoothing=0.01)  # the scenario default smoothing


@pytest.fixture(scope="module")
def logged(robot, tmp_path_factory):
    """A 4.5 s log of the Gen3 with the 6 lb dumbbell (θ_r perturbed, noise inside the bound)."""
    rng = np.random.default_rng(3)
    db = load_dumbbells(MODELS_DIR / "dumbbells.yaml")["6lb"]
    theta = E.perturbed_robot_theta(rng, robot, 0.05)
    truth = robot.theta_e + payload_theta_in_end_effector(db, robot.extra["grasp_point"])
    theta[robot.ee_slice] = truth
    t, q, v, tau, _ = E.simulate_log(rng, robot, theta, 4.5, 1000.0, centre=CENTRE)
    folder = tmp_path_factory.mktemp("sysid")
    path = write_joint_log(folder / "log.csv", JointLog(t, q, v, tau))
    scenario = folder / "s.yaml"
    scenario.write_text("name: sysid-test\npayload: {dumbbell: 6lb}\n")
    return path, scenario, truth, (t, q, v, tau)


def test_sysid_cli_writes_estimate_and_plots(logged, tmp_path, capsys):
    log, scenario, truth, _ = logged
    out = tmp_path / "out"
    assert main(["sysid", str(log), "--scenario", str(scenario), "--out", str(out)]) == 0
    doc = json.loads((out / "estimate.json").read_text())
    assert doc["contains_truth"] is True
    assert np.allclose(doc["truth"]["theta"], truth)
    lo, hi, nom = (np.array(doc["estimate"][k]) for k in ("lower", "upper", "nominal"))
    assert np.all(lo <= truth) and np.all(truth <= hi) and np.all(lo <= hi)
    assert abs(doc["mass_error_rel"]) < 0.02
    assert doc["sysid"]["updates"] == 3  # t_p = 1.5 s over 4.5 s
    assert doc["cond_Y"] > 1 and len(doc["widths"]) == 10 and doc["names"][0] == "m"
    for name in ("intervals.png", "history.png"):
        assert (out / name).stat().st_size > 10_000
    assert "truth inside: True" in capsys.readouterr().out


def _write(tmp_path, log, n_rows=None, mutate=None):
    t, q, v, tau = (x.copy() for x in log)
    if n_rows:
        t, q, v, tau = t[:n_rows], q[:n_rows], v[:n_rows], tau[:n_rows]
    if mutate:
        mutate(t, q, v, tau)
    return write_joint_log(tmp_path / "bad.csv", JointLog(t, q, v, tau))


def _run_bad(path, scenario, tmp_path, capsys):
    code = main(["sysid", str(path), "--scenario", str(scenario), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and str(path) in err
    return err


def test_nan_in_log(logged, tmp_path, capsys):
    _, scenario, _, data = logged
    path = _write(tmp_path, data, 2000, lambda t, q, v, tau: q.__setitem__((100, 3), np.nan))
    assert "NaN" in _run_bad(path, scenario, tmp_path, capsys)


def test_non_increasing_time(logged, tmp_path, capsys):
    _, scenario, _, data = logged
    path = _write(tmp_path, data, 2000, lambda t, q, v, tau: t.__setitem__(500, t[499]))
    assert "increasing" in _run_bad(path, scenario, tmp_path, capsys)


def test_wrong_joint_count(logged, tmp_path, capsys):
    _, scenario, _, (t, q, v, tau) = logged
    path = write_joint_log(tmp_path / "six.csv", JointLog(t[:2000], q[:2000, :6], v[:2000, :6], tau[:2000, :6]))
    assert "6 joints" in _run_bad(path, scenario, tmp_path, capsys)


def test_too_little_data_for_one_segment(logged, tmp_path, capsys):
    _, scenario, _, data = logged
    path = _write(tmp_path, data, 80)  # 0.08 s < one 0.1 s segment
    assert "too little data" in _run_bad(path, scenario, tmp_path, capsys)


def test_unknown_payload_in_scenario(logged, tmp_path, capsys):
    log, _, _, _ = logged
    bad = tmp_path / "bad.yaml"
    bad.write_text("payload: {dumbbell: 9lb}\n")
    code = main(["sysid", str(log), "--scenario", str(bad), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and "payload.dumbbell" in err
