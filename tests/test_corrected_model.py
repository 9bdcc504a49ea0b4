"""corrected_model.yaml as the model of a simulation: the scenario (`robot.corrected_model`)
loads its robot-side corrections into the RobotModel and its other effects into plant.effects,
and the simulated arm built from it, driven by the same commanded trajectory as the "real"
(Drake-simulated) arm, reproduces the real measured torque to the diagnosis' held-out RMS."""

import numpy as np
import pytest
import yaml
from safesysid.scenario import load_scenario
from safesysid.systems import diagnosis as dg
from safesysid.systems.config import ScenarioError
from safesysid.systems.model.loading import robot_from_scenario
from safesysid.systems.model.robot_model import MODELS_DIR, load_robot
from safesysid.systems.plant.arm_tracking import track_trajectory

URDF = MODELS_DIR / "kinova_gen3.urdf"
NOISE = {"torque_ratio": 0.01, "torque_floor_Nm": 0.05}
DURATION_S = 5.0


def write_corrected_model(path, model, diagnosis):
    """corrected_model.yaml (systems/model/corrected_model.py) of a diagnosis' significant effects."""
    effects = [
        {"name": e["name"], "joints": e["joints"], "params": e["params"]}
        for e in diagnosis.result["effects"]
        if e["significant"]
    ]
    path.write_text(yaml.safe_dump({"model": str(model), "effects": effects}, sort_keys=False))
    return path


def _scenario(folder, corrected, noise="none"):
    path = folder / "sim.yaml"
    path.write_text(
        f"robot: {{corrected_model: {corrected.name}}}\npayload: {{dumbbell: none}}\nnoise: {{distribution: {noise}}}\n"
    )
    return load_scenario(path)


def reproduce(tmp_path, effects, seed):
    """'Real' logs of the Gen3 (its friction and armature) with plant `effects`, diagnosed
    against the bare URDF (no friction, no armature: as the real Gen3 logs against RAPTOR's
    URDF); the corrected model's simulation of the held-out log's commanded trajectory vs that
    log. Returns (diagnosis, rms(sim - real), rms(log noise), rms(uncorrected sim - real))."""
    real = load_scenario(overrides={"payload": {"dumbbell": "none"}, "noise": NOISE, "plant": {"effects": effects}})
    controller = robot_from_scenario(real)  # the same commanded trajectory drives every plant
    rng = np.random.default_rng(seed)
    trajs = [dg.random_trajectory(controller, rng) for _ in range(3)]
    logs = [track_trajectory(real, controller, controller, tr, seed + k, DURATION_S) for k, tr in enumerate(trajs)]
    d = dg.diagnose(load_robot(model_path=URDF), logs[:2], logs[2:])
    check = logs[2]
    quiet = load_scenario(
        overrides={"payload": {"dumbbell": "none"}, "noise": {"distribution": "none"}, "plant": {"effects": effects}}
    )
    noise = check.tau - track_trajectory(quiet, controller, controller, trajs[2], seed + 2, DURATION_S).tau
    rms = {}
    for name, diagnosis in (("corrected", d), ("uncorrected", None)):
        folder = tmp_path / name
        folder.mkdir()
        corrected = (
            write_corrected_model(folder / "corrected_model.yaml", URDF, diagnosis)
            if diagnosis
            else _write_empty(folder / "corrected_model.yaml")
        )
        s = _scenario(folder, corrected)
        sim = track_trajectory(s, robot_from_scenario(s), controller, trajs[2], 99, DURATION_S)
        assert np.array_equal(sim.t, check.t)
        rms[name] = float(np.sqrt(np.mean((sim.tau - check.tau) ** 2)))
    return d, rms["corrected"], float(np.sqrt(np.mean(noise**2))), rms["uncorrected"]


def _write_empty(path):
    path.write_text(yaml.safe_dump({"model": str(URDF), "effects": []}))
    return path


# Closed loop: the PD supplies a model error delta as torque through its complementary
# sensitivity, |T| slightly above 1 near the loop's bandwidth, so the simulated torque may
# differ from the real one by a little more than the held-out residual (measured 1.08x).
CLOSED_LOOP = 1.25


def test_lagged_sensor_is_reproduced(tmp_path):
    """A first-order lag of the torque sensor (the real Gen3's filtered torque): diagnosed as
    the injected time constant and fed back to the simulated arm, the corrected simulation
    reproduces the logged torque to the held-out RMS plus the log's noise. (Before the sensor
    output was the filter state, the simulated sensor led the continuous law by one plant
    step: 0.08 s was diagnosed as 0.079 s and the corrected simulation missed by 0.072 N m
    against a reported 0.0125 N m.)"""
    d, rms, noise, before = reproduce(tmp_path, {"torque_sensor_lag_s": 0.08}, seed=30)
    lag = next(e for e in d.result["effects"] if e["name"] == "time_delay")
    assert lag["significant"] and lag["params"]["law"].startswith("first-order")
    assert lag["params"]["delay_s"] == pytest.approx(0.08, abs=5e-4)
    after = d.result["combined"]["rms_check_after"]
    print(
        f"lag: held-out RMS {d.result['gap']['rms_check']:.3f} -> {after:.4f} N m; corrected simulation vs log "
        f"{rms:.4f} N m (log noise {noise:.4f}); uncorrected simulation {before:.2f} N m"
    )
    assert rms <= CLOSED_LOOP * after + noise
    assert before > 20 * (CLOSED_LOOP * after + noise)  # not vacuous


def test_corrected_model_reproduces_the_logged_torque(tmp_path):
    """The bare URDF against an arm with friction, armature, a lagged torque sensor and load
    friction: all named, and the corrected model (robot side: Fc, Fv, Ia; plant side: lag, load
    friction) simulated along the held-out log's commanded trajectory reproduces its torque."""
    mu = [0.0, 0.08, 0.0, 0.06, 0.0, 0.0, 0.0]
    d, rms, noise, before = reproduce(tmp_path, {"torque_sensor_lag_s": 0.08, "load_friction_mu": mu}, seed=3)
    assert set(d.result["cause"]) == {"armature", "time_delay", "viscous_friction", "load_friction", "coulomb_friction"}
    after = d.result["combined"]["rms_check_after"]
    print(
        f"full: held-out RMS {d.result['gap']['rms_check']:.3f} -> {after:.4f} N m; corrected simulation vs log "
        f"{rms:.4f} N m (log noise {noise:.4f}); uncorrected simulation {before:.2f} N m"
    )
    assert rms <= CLOSED_LOOP * after + noise
    assert before > 20 * (CLOSED_LOOP * after + noise)


def test_scenario_loads_both_sides(tmp_path):
    doc = {
        "model": str(URDF),
        "effects": [
            {"name": "viscous_friction", "joints": [1], "params": {"delta_Fv_Nms_rad": [2.0] + [0.0] * 6}},
            {"name": "armature", "joints": [2], "params": {"delta_Ia_kgm2": [0.0, 3.0] + [0.0] * 5}},
            {"name": "torque_offset", "joints": [3], "params": {"offset_Nm": [0, 0, 0.5, 0, 0, 0, 0]}},
            {"name": "time_delay", "joints": [1], "params": {"delay_s": 0.1, "law": "first-order lag: tau_meas + ..."}},
            {"name": "load_friction", "joints": [4], "params": {"mu": [0, 0, 0, 0.1, 0, 0, 0]}},
            {"name": "joint_elasticity", "joints": [2], "params": {"compliance_rad_per_Nm": [0, 0.002, 0, 0, 0, 0, 0]}},
            {"name": "torque_scale", "joints": [5], "params": {"scale": [1, 1, 1, 1, 1.05, 1, 1]}},
            {
                "name": "base_tilt",  # as diagnose writes it: gravity in the base frame, and the angles
                "joints": [1],
                "params": {
                    "gravity_xy_over_g": [-0.01999866669333308, -0.009997833434164497],
                    "roll_rad": 0.01,
                    "pitch_rad": -0.02,
                },
            },
            {
                "name": "stribeck_friction",
                "joints": [6],
                "params": {"Fs_Nm": [0, 0, 0, 0, 0, 1.0, 0], "vs_rad_s": 0.03},
            },
        ],
    }
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(doc))
    (tmp_path / "s.yaml").write_text("robot: {corrected_model: c.yaml, coulomb_smoothing_rad_s: 0.02}\n")
    s = load_scenario(tmp_path / "s.yaml")
    robot = robot_from_scenario(s)
    bare = load_robot(model_path=URDF)
    jp = robot.joint_params
    assert jp.viscous[0] == 2.0 and jp.armature[1] == 3.0 and jp.offset[2] == 0.5 and robot.source == str(URDF)
    assert np.array_equal(robot.theta[:70], bare.theta[:70]) and np.array_equal(robot.theta[70:], jp.friction_theta())
    assert robot.coulomb_smoothing == 0.02
    e = s.plant.effects
    assert e.torque_sensor_lag_s == 0.1 and e.load_friction_mu[3] == 0.1 and e.torque_sensor_scale[4] == 1.05
    assert s.estimator.torque_lag_s == 0.1  # the estimator reads the same sensor model
    assert e.joint_stiffness_Nm_rad[1] == pytest.approx(500.0) and e.joint_stiffness_Nm_rad[0] >= 1e12
    assert e.base_tilt_rad == [0.01, -0.02] and e.stribeck_friction_Nm[5] == 1.0 and e.stribeck_velocity_rad_s == 0.03
    assert e.torque_sensor_offset_Nm == []  # the offset is the model's beta, counted once


@pytest.mark.parametrize(
    "scenario, effects, expect",
    [
        ("robot: {corrected_model: missing.yaml}", None, "robot.corrected_model: file 'missing.yaml' not found"),
        ("robot: {corrected_model: c.yaml, model: x.urdf}", [], "robot.model: not with robot.corrected_model"),
        (
            "robot: {corrected_model: c.yaml}\nplant: {effects: {torque_sensor_lag_s: 0.1}}",
            [{"name": "time_delay", "joints": [1], "params": {"delay_s": 0.05, "time_law": "lag"}}],
            "plant.effects.torque_sensor_lag_s: also set by robot.corrected_model",
        ),
        (
            "robot: {corrected_model: c.yaml}\nestimator: {torque_lag_s: 0.1}",
            [{"name": "time_delay", "joints": [1], "params": {"delay_s": 0.05, "time_law": "lag"}}],
            "estimator.torque_lag_s: also set by robot.corrected_model",
        ),
        (
            "robot: {corrected_model: c.yaml}\nestimator: {torque_signal: continuous}",
            [{"name": "time_delay", "joints": [1], "params": {"delay_s": 0.05, "time_law": "lag"}}],
            "estimator.torque_lag_s: needs estimator.torque_signal: held",
        ),
        (
            "robot: {corrected_model: c.yaml}\nestimator: {torque_delay_s: 0.02}",
            [{"name": "time_delay", "joints": [1], "params": {"delay_s": -0.02, "time_law": "shift"}}],
            "estimator.torque_delay_s: also set by robot.corrected_model",
        ),
        (
            "robot: {corrected_model: c.yaml}",
            [{"name": "payload", "joints": [7], "params": {"theta_delta": [0.1] * 10}}],
            "effects[0] payload",
        ),
        (
            "robot: {corrected_model: c.yaml}",
            [{"name": "load_friction", "joints": [1], "params": {}}],
            "effects[0].params.mu: missing",
        ),
    ],
)
def test_bad_corrected_models_are_named(tmp_path, scenario, effects, expect):
    if effects is not None:
        (tmp_path / "c.yaml").write_text(yaml.safe_dump({"model": str(URDF), "effects": effects}))
    (tmp_path / "s.yaml").write_text(scenario + "\n")
    with pytest.raises(ScenarioError, match="s.yaml: ") as err:
        robot_from_scenario(load_scenario(tmp_path / "s.yaml"))
    assert expect in str(err.value) and "\n" not in str(err.value)


def test_a_diagnosed_lag_interval_is_the_estimators_lag_interval(tmp_path):
    """A lag effect with `intervals.delay_s` (the diagnosis' uncertainty of its lag): the simulated
    arm's sensor takes the point value, the estimator (robot.corrected_model, and `sysid --model`
    through model_corrections.torque_lag_s) the interval, widened to hold the point; null (no
    information) falls back to the point, and lo > hi is named."""
    from safesysid.sysid_cli import corrected_model
    from safesysid.systems.model.corrections import CorrectionError, read_correction, torque_lag_s

    def lag_model(pair):
        effect = {"name": "time_delay", "joints": [1], "params": {"delay_s": 0.1, "time_law": "lag"}}
        (tmp_path / "c.yaml").write_text(
            yaml.safe_dump({"model": str(URDF), "effects": [{**effect, "intervals": {"delay_s": pair}}]})
        )
        return tmp_path / "c.yaml"

    lag_model([0.09, 0.12])
    (tmp_path / "s.yaml").write_text("robot: {corrected_model: c.yaml}\n")
    scene = load_scenario(tmp_path / "s.yaml")
    assert scene.plant.effects.torque_sensor_lag_s == 0.1 and scene.estimator.torque_lag_s == [0.09, 0.12]
    assert corrected_model(lag_model([0.105, 0.12]))[1] == [0.1, 0.12]  # the point inside
    assert torque_lag_s(read_correction(lag_model([None, None]))) == 0.1
    with pytest.raises(CorrectionError, match=r"c.yaml: effects\[0\].intervals.delay_s"):
        torque_lag_s(read_correction(lag_model([0.12, 0.09])))


@pytest.mark.parametrize("delay, field", [(0.03, "torque_sensor_delay_s"), (-0.02, "time_delay_s")])
def test_pure_delays_map_to_the_sensor_or_the_actuation(tmp_path, delay, field):
    """Torque lagging the motion (d > 0) is a late sensor reading; leading it, an actuation delay.
    The estimator re-pairs each step with its torque by the same signed shift."""
    doc = {
        "model": str(URDF),
        "effects": [
            {"name": "time_delay", "joints": [1], "params": {"delay_s": delay, "law": "pure delay tau(t - d)"}}
        ],
    }
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(doc))
    (tmp_path / "s.yaml").write_text("robot: {corrected_model: c.yaml}\n")
    scene = load_scenario(tmp_path / "s.yaml")
    assert getattr(scene.plant.effects, field) == abs(delay) and scene.estimator.torque_delay_s == delay


def test_joint_count_is_checked(tmp_path):
    doc = {
        "model": str(URDF),
        "effects": [{"name": "viscous_friction", "joints": [1], "params": {"delta_Fv_Nms_rad": [1.0, 2.0]}}],
    }
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(doc))
    (tmp_path / "s.yaml").write_text("robot: {corrected_model: c.yaml}\n")
    with pytest.raises(ScenarioError, match=r"effects\[0\].params.delta_Fv_Nms_rad: 2 values for a model with 7"):
        robot_from_scenario(load_scenario(tmp_path / "s.yaml"))


def test_late_torque_reading_is_diagnosed_as_its_delay():
    """torque_sensor_delay_s (the counterpart of a diagnosed pure delay with d > 0): 0.03 s in
    the simulated arm is diagnosed blind as a 0.03 s pure delay, so it maps back one to one."""
    real = load_scenario(
        overrides={
            "payload": {"dumbbell": "none"},
            "noise": NOISE,
            "plant": {"effects": {"torque_sensor_delay_s": 0.03}},
        }
    )
    robot = robot_from_scenario(real)
    rng = np.random.default_rng(4)
    logs = [track_trajectory(real, robot, robot, dg.random_trajectory(robot, rng), 20 + k, 4.0) for k in range(3)]
    d = dg.diagnose(robot, logs[:2], logs[2:])
    assert d.result["cause"] == ["time_delay"]
    params = next(e for e in d.result["effects"] if e["name"] == "time_delay")["params"]
    assert params["law"].startswith("pure delay") and params["delay_s"] == pytest.approx(0.03, abs=5e-4)


def test_the_starting_model_is_stored_relative_so_a_diagnosis_folder_can_move(tmp_path):
    """The written model_resolved is relative to the YAML's folder (an absolute path breaks as soon
    as the folder is copied to another machine), and the moved pair still finds its model."""
    import shutil

    from safesysid.systems.model.corrected_model import CorrectedModel, read_corrected_model

    here = tmp_path / "lab"
    (here / "models").mkdir(parents=True)
    shutil.copy(URDF, here / "models" / "arm.urdf")
    model = CorrectedModel(model="arm.urdf", model_resolved=str((here / "models" / "arm.urdf").resolve()))
    (here / "out").mkdir()
    dg.write_corrected_model(here / "out" / "corrected_model.yaml", model)
    written = yaml.safe_load((here / "out" / "corrected_model.yaml").read_text())
    assert written["model_resolved"] == "../models/arm.urdf"
    moved = shutil.copytree(here, tmp_path / "elsewhere")
    shutil.rmtree(here)
    found = read_corrected_model(moved / "out" / "corrected_model.yaml").model_path()
    assert found == moved / "out" / ".." / "models" / "arm.urdf" and found.is_file()
