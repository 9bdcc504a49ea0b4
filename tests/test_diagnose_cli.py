"""`safesysid diagnose` end to end: contract fields, report, plots, corrected parameters,
bad input -> one line, exit 2."""

import json

import numpy as np
import pytest
from safesysid.cli import main
from safesysid.joint_log import write_joint_log
from safesysid.systems import diagnosis as dg
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.robot_model import load_robot
from test_gap import TWO_LINK


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A 2-link arm URDF and three logs with viscous friction on joint 1 withheld."""
    root = tmp_path_factory.mktemp("diag")
    urdf = root / "two_link.urdf"
    urdf.write_text(TWO_LINK)
    model = load_robot(model_path=urdf)
    rng = np.random.default_rng(21)
    paths = []
    for k in range(3):
        traj = dg.random_trajectory(model, rng)
        t = dg.sample_times(rng, 10.0)
        q, v, a, tau = dg.true_torque(model, traj, t, effects={"viscous_friction": {"delta": np.array([1.5, 0.0])}})
        tau = tau + 0.2 * rng.uniform(-1, 1, tau.shape)
        paths.append(write_joint_log(root / f"log{k}.csv", JointLog(t, q, v, tau, a if k != 1 else None)))
    return root, urdf, paths


def test_diagnose_writes_the_contract(case, capsys):
    root, urdf, (a, b, c) = case
    out = root / "out"
    assert main(["diagnose", "--model", str(urdf), "--fit", str(a), str(b), "--check", str(c), "--out", str(out)]) == 0
    res = json.loads((out / "diagnosis.json").read_text())
    g = res["gap"]
    for key in ("rms_fit", "rms_check", "rms_check_per_joint", "where"):
        assert key in g
    assert len(g["rms_check_per_joint"]) == 2 and set(g["where"]["joints"]) == {1, 2}
    assert set(g["where"]["regimes"]) >= {"near_zero_velocity", "high_acceleration", "high_speed", "high_gravity_load"}
    assert [e["name"] for e in res["effects"]][0] == "viscous_friction"
    assert sorted(e["name"] for e in res["effects"]) == sorted(dg.EFFECTS)
    for e in res["effects"]:
        assert set(e) >= {"name", "joints", "params", "rms_check_after", "reduction", "significant"}
        assert 0.0 <= e["reduction"] <= 1.0
    assert res["cause"] == ["viscous_friction"]
    comb = res["combined"]
    assert comb["effects"] == ["viscous_friction"] and comb["reduction"] > 0.5
    assert len(comb["rms_check_per_joint_after"]) == 2
    # One log has no accelerations -> the whole diagnosis uses the momentum form, and the
    # differentiator comparison is reported.
    assert g["residual_form"] == "momentum"
    assert "inverse_dynamics_smoothed_a" in next(iter(g["residual_forms"].values()))
    report = (out / "report.md").read_text()
    assert "viscous_friction" in report and f"{g['rms_check']:.3f}" in report
    for name in (
        "residual_vs_velocity.png",
        "residual_vs_acceleration.png",
        "residual_vs_gravity.png",
        "residual_timeseries.png",
        "joint_rms.png",
    ):
        assert (out / name).stat().st_size > 1000
    # Feed back: the corrected parameters load as a joint-parameter YAML with the fitted friction.
    fixed = load_robot(params_path=out / "corrected_params.yaml")
    assert fixed.joint_params.viscous[0] == pytest.approx(1.5, abs=0.2)
    assert fixed.joint_params.viscous[1] == pytest.approx(0.0, abs=1e-12)
    assert "held-out (test) RMS" in capsys.readouterr().out
    # Honest protocol: the check-log numbers are `test`, the inner folds' `cross_validation`.
    assert res["test"]["rms_after"] == comb["rms_check_after"] and res["test"]["logs"] == [str(c)]
    assert res["cross_validation"]["scheme"] == "leave_one_fit_log_out"
    assert [f["validate"] for f in res["cross_validation"]["folds"]] == [[str(a)], [str(b)]]
    # The verdict opens the report: where, why (values with units), held-out shrinkage.
    head = report.split("\n\n")[1:4]
    assert head[0].startswith("**Where:**") and "joint" in head[0]
    assert head[1].startswith("**Why:**") and "viscous friction Fv" in head[1] and "N·m·s/rad" in head[1]
    assert head[2].startswith("**Held-out (test):**") and f"{100 * comb['reduction']:.1f} % less" in head[2]
    assert (out / "corrected_model.yaml").is_file() and (out / "report.html").is_file()


def test_corrected_model_closes_the_gap(case):
    """Diagnosing again with the corrected parameters leaves nothing significant."""
    root, urdf, (a, b, c) = case
    from safesysid.joint_log import read_joint_log

    out = root / "out2"
    assert main(["diagnose", "--model", str(urdf), "--fit", str(a), str(b), "--check", str(c), "--out", str(out)]) == 0
    fixed = load_robot(params_path=out / "corrected_params.yaml")
    logs = [read_joint_log(p, 2) for p in (a, b, c)]
    d = dg.diagnose(fixed, logs[:2], logs[2:])
    assert d.result["cause"] == []


def test_leave_one_out_pools_the_folds(case, capsys):
    """--leave-one-out: each log held out once; a diagnosis folder per fold and the pooled
    held-out numbers (pooled over every held-out row, the mean over folds, the effects named in
    every fold) agreeing with the folds' own diagnosis.json."""
    root, urdf, paths = case
    out = root / "loo"
    assert (
        main(["diagnose", "--model", str(urdf), "--leave-one-out", "--fit", *map(str, paths), "--out", str(out)]) == 0
    )
    res = json.loads((out / "leave_one_out.json").read_text())
    folds = [json.loads((out / f"fold{k + 1}_log{k}" / "diagnosis.json").read_text()) for k in range(3)]
    assert [f["check"] for f in res["folds"]] == [[str(p)] for p in paths]
    for f, d in zip(res["folds"], folds):
        assert f["rms_before"] == pytest.approx(d["gap"]["rms_check"])
        assert f["rms_after"] == pytest.approx(d["combined"]["rms_check_after"])
        assert f["cause"] == d["cause"] == ["viscous_friction"]
    before = [f["rms_before"] for f in res["folds"]]
    assert min(before) <= res["pooled"]["rms_before"] <= max(before)
    assert res["mean_over_folds"]["rms_before"] == pytest.approx(np.mean(before))
    assert res["pooled"]["reduction"] > 0.5 and res["pooled"]["reduction_per_joint"][0] > 0.5
    assert res["named_in_every_fold"] == ["viscous_friction"] and res["named_in_some_fold"] == []
    report = (out / "report.md").read_text()
    assert "fold1_log0/report.md" in report and f"{100 * res['pooled']['reduction']:.1f}%" in report
    assert "pooled over 3 folds" in capsys.readouterr().out
    assert (out / "report.html").is_file() and (out / "fold1_log0" / "corrected_model.yaml").is_file()


def _one_line_exit_2(argv, capsys, needle):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err


def test_bad_input_is_one_line_exit_2(case, tmp_path, capsys):
    root, urdf, (a, b, c) = case
    base = ["diagnose", "--model", str(urdf), "--out", str(tmp_path / "o")]
    text = a.read_text().splitlines()
    header = text[0].split(",")
    # Missing column.
    drop = header.index("tau2")
    bad = tmp_path / "missing.csv"
    bad.write_text("\n".join(",".join(x for k, x in enumerate(r.split(",")) if k != drop) for r in text))
    _one_line_exit_2(base + ["--fit", str(bad), "--check", str(c)], capsys, "tau2")
    # NaN.
    rows = [r.split(",") for r in text]
    rows[5][2] = "nan"
    nan = tmp_path / "nan.csv"
    nan.write_text("\n".join(",".join(r) for r in rows))
    _one_line_exit_2(base + ["--fit", str(nan), "--check", str(c)], capsys, "NaN")
    # Joint count different from the model (the 7-joint Kinova).
    kin = tmp_path / "kinova.yaml"
    kin.write_text("name: k\n")
    _one_line_exit_2(
        ["diagnose", "--model", str(kin), "--fit", str(a), "--check", str(c), "--out", str(tmp_path / "o")],
        capsys,
        "joints",
    )
    # A URDF that does not load.
    broken = tmp_path / "broken.urdf"
    broken.write_text(
        "<robot name='x'><link name='a'/><joint name='j' type='revolute'><parent link='a'/></joint></robot>"
    )
    _one_line_exit_2(
        ["diagnose", "--model", str(broken), "--fit", str(a), "--check", str(c), "--out", str(tmp_path / "o")],
        capsys,
        "broken.urdf",
    )
    # No model.
    _one_line_exit_2(["diagnose", "--fit", str(a), "--check", str(c)], capsys, "--model")
    _one_line_exit_2(base[:3] + ["--leave-one-out", "--fit", str(a)], capsys, "--leave-one-out")


def test_self_check_cli(tmp_path, capsys):
    out = tmp_path / "sc"
    assert main(["diagnose", "--self-check", "--cases", "2", "--seed", "3", "--out", str(out)]) == 0
    res = json.loads((out / "self_check.json").read_text())
    assert res["summary"]["cases"] == 2 and res["summary"]["null_cases"] == 1
    assert res["cases"][0]["injected"] == [] and res["cases"][0]["named"] == []
    assert "injected \\ named" in (out / "confusion.md").read_text()
    assert "injected effects named" in capsys.readouterr().out


def test_scenario_yaml_as_model(tmp_path, capsys):
    """MODEL may be a scenario YAML: its robot (the project's Kinova Gen3) is diagnosed."""
    scenario = tmp_path / "s.yaml"
    scenario.write_text("name: diag\n")
    model = load_robot()
    rng = np.random.default_rng(5)
    paths = []
    for k in range(2):
        traj = dg.random_trajectory(model, rng)
        t = dg.sample_times(rng, 6.0)
        q, v, a, tau = dg.true_torque(
            model, traj, t, effects={"torque_offset": {"delta": np.r_[0, 2.0, 0, 0, 0, 0, 0]}}
        )
        tau = tau + 0.2 * rng.uniform(-1, 1, tau.shape)
        paths.append(write_joint_log(tmp_path / f"k{k}.csv", JointLog(t, q, v, tau, a)))
    out = tmp_path / "out"
    assert (
        main(
            ["diagnose", "--model", str(scenario), "--fit", str(paths[0]), "--check", str(paths[1]), "--out", str(out)]
        )
        == 0
    )
    res = json.loads((out / "diagnosis.json").read_text())
    assert res["cause"] == ["torque_offset"]
    assert next(e for e in res["effects"] if e["name"] == "torque_offset")["joints"] == [2]


def test_corrected_model_is_scored_frozen_on_new_logs(case, capsys, monkeypatch):
    """`--model corrected_model.yaml --check X` reproduces the test RMS diagnose reported for X
    (to 1e-6, per joint too) and fits nothing (the fitting functions raise if called)."""
    root, urdf, (a, b, c) = case
    out = root / "frozen_src"
    assert main(["diagnose", "--model", str(urdf), "--fit", str(a), str(b), "--check", str(c), "--out", str(out)]) == 0
    ref = json.loads((out / "diagnosis.json").read_text())

    def no_fitting(*args, **kwargs):
        raise AssertionError("a frozen model must not be fitted")

    monkeypatch.setattr(dg.problem, "fit_effects", no_fitting)
    monkeypatch.setattr(dg.cross_validation, "fit_effects", no_fitting)
    monkeypatch.setattr(dg.Problem, "solve", no_fitting)
    capsys.readouterr()
    scored = root / "frozen_out"
    assert (
        main(["diagnose", "--model", str(out / "corrected_model.yaml"), "--check", str(c), "--out", str(scored)]) == 0
    )
    res = json.loads((scored / "diagnosis.json").read_text())
    assert abs(res["combined"]["rms_check_after"] - ref["combined"]["rms_check_after"]) < 1e-6
    assert (
        np.abs(
            np.subtract(res["combined"]["rms_check_per_joint_after"], ref["combined"]["rms_check_per_joint_after"])
        ).max()
        < 1e-6
    )
    assert res["cause"] == ref["cause"] and res["frozen"]["fitted"] == "nothing"
    printed = capsys.readouterr().out
    assert "nothing fitted" in printed and f"{ref['combined']['rms_check_after']:.6f}" in printed
    assert "nothing fitted" in (scored / "report.md").read_text()


def test_corrected_model_bad_input_is_one_line_exit_2(case, tmp_path, capsys):
    """A corrected model with a missing or malformed field, a missing starting model or a joint
    count that does not match: one line naming file and field, exit 2."""
    import yaml

    root, urdf, (a, b, c) = case
    out = root / "bad_src"
    assert main(["diagnose", "--model", str(urdf), "--fit", str(a), str(b), "--check", str(c), "--out", str(out)]) == 0
    doc = yaml.safe_load((out / "corrected_model.yaml").read_text())
    capsys.readouterr()

    def run_with(mutate, needle, extra=()):
        bad = yaml.safe_load(yaml.safe_dump(doc))
        mutate(bad)
        path = tmp_path / "corrected_model.yaml"
        path.write_text(yaml.safe_dump(bad))
        _one_line_exit_2(
            ["diagnose", "--model", str(path), "--check", str(c), *extra, "--out", str(tmp_path / "o")], capsys, needle
        )

    run_with(lambda d: d["effects"][0]["params"].pop("delta_Fv_Nms_rad"), "effects[0].params.delta_Fv_Nms_rad")
    run_with(lambda d: d["effects"][0].update(name="magic"), "effects[0].name")
    run_with(
        lambda d: d["effects"][0]["params"].update(delta_Fv_Nms_rad=[1.0, 2.0, 3.0]),
        "effects[0].params.delta_Fv_Nms_rad",
    )
    run_with(lambda d: d.update(model="nowhere.urdf", model_resolved=""), "model")
    run_with(lambda d: d["scoring"].update(residual_form="magic"), "scoring.residual_form")
    run_with(lambda d: None, "--check only", extra=("--fit", str(a)))


def test_report_html_renders_in_headless_chromium(case):
    """report.html is self-contained: headless Chromium decodes every embedded plot (the page
    records the count after load) and shows the verdict."""
    import shutil
    import subprocess

    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        pytest.skip("chromium not installed (apt-get install -y chromium)")
    root, urdf, (a, b, c) = case
    out = root / "html"
    assert main(["diagnose", "--model", str(urdf), "--fit", str(a), str(b), "--check", str(c), "--out", str(out)]) == 0
    page = (out / "report.html").read_text()
    n_images = page.count("<img ")
    assert n_images >= 5 and 'src="data:image/png;base64,' in page and '.png"' not in page
    dom = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom", (out / "report.html").as_uri()],
        capture_output=True,
        text=True,
        timeout=120,
    ).stdout
    assert f'data-images-decoded="{n_images}"' in dom
    assert "Where:" in dom and "Held-out (test):" in dom
