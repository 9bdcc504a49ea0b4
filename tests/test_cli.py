"""The command line: verbs listed, bad input is one line naming file and field, exit 2."""

import subprocess
import sys

import pytest
from safesysid.cli import main


def run(*args):
    proc = subprocess.run([sys.executable, "-m", "safesysid.cli", *args], capture_output=True, text=True, timeout=300)
    return proc.returncode, proc.stdout, proc.stderr


def test_help_lists_the_verbs():
    code, out, _ = run("--help")
    assert code == 0
    for verb in ("run", "compare", "sysid", "diagnose", "bench"):
        assert verb in out


@pytest.mark.parametrize(
    "yaml_text, field",
    [
        ("planner: {num_plans: many}", "planner.num_plans"),
        ("payload: {dumbbell: 9lb}", "payload.dumbbell"),
        ("obstacles: [{size_m: [0.1, 0.1, -1]}]", "obstacles[0].size_m"),
    ],
)
def test_bad_scenario_exits_2_with_one_line(tmp_path, yaml_text, field):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml_text)
    code, out, err = run("run", str(path), "--out", str(tmp_path / "out"))
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and field in lines[0]


def test_bad_method_exits_2(tmp_path, capsys):
    assert main(["run", "--method", "best", "--out", str(tmp_path)]) == 2
    assert "--method" in capsys.readouterr().err


@pytest.mark.parametrize(
    "verb",
    [
        ["run"],
        ["compare", "scenarios/quickstart.yaml"],
        ["sweep", "scenarios/quickstart.yaml"],
        ["sysid", "no_log.csv"],
    ],
)
def test_scenario_text_is_a_layer_on_every_scenario_verb(tmp_path, capsys, verb):
    """--scenario-text reaches the loader (a bad key in it exits 2 naming it) on each verb."""
    from safesysid.scenario import SCENARIOS_DIR

    args = [a.replace("scenarios/", f"{SCENARIOS_DIR}/") for a in verb]
    code = main(
        [*args, "--out", str(tmp_path), "--scenario-text", "seed: 4", "--scenario-text", "noise: {torque_rato: 0.1}"]
    )
    err = capsys.readouterr().err
    assert code == 2 and "--scenario-text[1]: noise.torque_rato: unknown key" in err, err


def test_scenario_text_changes_only_the_keys_it_names():
    from safesysid.cli import build_parser
    from safesysid.run_cli import _scenario

    args = build_parser().parse_args(
        ["run", "--scenario-text", "noise: {torque_floor_Nm: 0.1}", "--scenario-text", "seed: 7"]
    )
    s = _scenario(args)
    assert s.name == "quickstart" and s.seed == 7 and s.payload.dumbbell == "4lb"
    assert (s.noise.torque_ratio, s.noise.torque_floor_Nm) == (0.025, 0.1)
