"""Effects of the simulated arm that the diagnosis names but the robot model has no term for:
load-dependent friction mu |tau| sgn v and Stribeck friction Fs sgn v exp(-(v/vs)^2), both in the
diagnosis' law (systems/dg.py), and a late torque reading, as plant.effects of the real arm."""

import json

import numpy as np
import pytest
from helpers import FULL
from pydrake.systems.framework import DiagramBuilder
from safesysid.cli import main
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.systems import diagnosis as dg
from safesysid.systems.config import ScenarioError
from safesysid.systems.model.loading import robot_from_scenario
from safesysid.systems.model.regressors import coulomb_shape, friction_columns
from safesysid.systems.plant.station import add_real_arm

MU = [0.0, 0.12, 0.0, 0.1, 0.0, 0.0, 0.0]


@pytest.fixture(scope="module")
def robot():
    return robot_from_scenario(load_scenario())


def test_joint_friction_follows_the_diagnosis_law(robot):
    """Generalized force = applied - (Fc sgn v + Fv v + beta) - mu |applied| sgn v
    - Fs sgn v exp(-(v/vs)^2), sgn the model's (smoothed) Coulomb shape, as gap's columns."""
    fs, vs = [0.0, 2.0, 0.0, 0.0, 1.5, 0.0, 0.0], 0.05
    s = load_scenario(
        overrides={
            "plant": {"effects": {"load_friction_mu": MU, "stribeck_friction_Nm": fs, "stribeck_velocity_rad_s": vs}}
        }
    )
    b = DiagramBuilder()
    arm = add_real_arm(b, s, robot=robot)
    friction = arm.system.GetSubsystemByName("joint_friction")  # inside the real_arm station
    ctx = friction.CreateDefaultContext()
    rng = np.random.default_rng(2)
    v = rng.normal(scale=0.05, size=7)
    tau = rng.normal(scale=20.0, size=7)
    friction.applied.FixValue(ctx, tau)
    friction.state.FixValue(ctx, np.concatenate([np.zeros(7), v]))
    sgn = coulomb_shape(v, robot.coulomb_smoothing)
    law = (
        friction_columns(v[None], a=np.zeros((1, 7)), kind="standard", smoothing_velocity=robot.coulomb_smoothing)[0]
        @ robot.theta[70:]
    )
    law = law + np.array(MU) * np.abs(tau) * sgn + np.array(fs) * sgn * np.exp(-((v / vs) ** 2))
    np.testing.assert_allclose(friction.get_output_port().Eval(ctx), tau - law, rtol=1e-12, atol=1e-12)


def test_bad_friction_effects_are_named():
    with pytest.raises(ScenarioError, match="plant.effects.load_friction_mu"):
        load_scenario(overrides={"plant": {"effects": {"load_friction_mu": [0.0, -0.1] + [0.0] * 5}}})
    with pytest.raises(ScenarioError, match="plant.effects.stribeck_velocity_rad_s"):
        load_scenario(
            overrides={"plant": {"effects": {"stribeck_friction_Nm": [1.0] * 7, "stribeck_velocity_rad_s": 0.0}}}
        )


@pytest.mark.slow
@pytest.mark.skipif(not FULL, reason="3 Drake logs through diagnosis.real_arm_log (~60 s); SAFESYSID_FULL=1")
def test_load_friction_of_the_simulated_arm_is_diagnosed_blind():
    """Drake-simulated logs with load friction on joints 2 and 4: the diagnosis names it, on
    those joints, with mu near the injected value (its law is the plant's)."""
    runs = [dg.real_arm_log({"load_friction_mu": MU}, seed=70 + k, duration_s=6.0) for k in range(3)]
    logs, robot = [log for log, _ in runs], runs[0][1]
    d = dg.diagnose(robot, logs[:2], logs[2:])
    assert d.result["cause"] == ["load_friction"], d.result["cause"]
    entry = next(e for e in d.result["effects"] if e["name"] == "load_friction")
    assert set(entry["joints"]) == {2, 4}
    mu = np.array(entry["params"]["mu"])
    np.testing.assert_allclose(mu[[1, 3]], np.array(MU)[[1, 3]], rtol=0.15)
    assert d.result["combined"]["reduction"] > 0.8


def test_late_torque_reading(robot):
    """torque_sensor_delay_s: the measured torque is the reading of d earlier, noise included
    (zero before); the motion is unchanged. The command feeds back the state, so a delay stage
    that sampled after the plant's step would store a torque the arm never received."""
    for delay in (0.001, 0.004):
        runs = {name: _feedback_run(robot, {"torque_sensor_delay_s": d}) for name, d in (("late", delay), ("plain", 0))}
        steps = int(round(delay / 0.001))
        (late, x_late, _), (plain, x_plain, _) = runs["late"], runs["plain"]
        np.testing.assert_array_equal(late[steps:], plain[:-steps])
        assert np.all(late[:steps] == 0)
        np.testing.assert_array_equal(x_late, x_plain)


def test_late_actuation(robot):
    """time_delay_s: the joint receives the motor torque of d earlier (zero before), exactly,
    under a state-feedback command."""
    for delay in (0.001, 0.003):
        steps = int(round(delay / 0.001))
        _, _, (motor, applied, _) = _feedback_run(robot, {"time_delay_s": delay})
        np.testing.assert_array_equal(applied[steps:], motor[:-steps])
        assert np.all(applied[:steps] == 0)


def test_quasi_static_elasticity_under_state_feedback(robot):
    """joint_stiffness_Nm_rad (quasi_static) under a command that feeds back the encoders: no
    algebraic loop, and the encoders read q + tau_s / K with tau_s the torque the transmission
    carried over the step that just ended (applied torque minus the model's friction law); the
    first reading holds the torque transmitted at initialization (commanded from q itself)."""
    stiffness = np.array([1e4] * 4 + [4e3] * 3)
    jp = robot.joint_params
    _, encoders, (_, applied, plant_state) = _feedback_run(robot, {"joint_stiffness_Nm_rad": stiffness.tolist()})
    v = plant_state[:, 7:]
    transmitted = applied - (jp.coulomb * np.tanh(v / robot.coulomb_smoothing) + jp.viscous * v + jp.offset)
    np.testing.assert_array_equal(encoders[:, 7:], v)
    offset = encoders[:, :7] - plant_state[:, :7]
    np.testing.assert_allclose(offset[1:], transmitted[:-1] / stiffness, rtol=0, atol=1e-12)
    np.testing.assert_allclose(offset[0], transmitted[0] / stiffness, rtol=0.01, atol=1e-12)
    assert np.abs(np.diff(transmitted, axis=0)).max() > 0.05  # the torque changes: one step late is seen


def test_quickstart_runs_with_quasi_static_elasticity(tmp_path):
    """The app's own loop (ARMOUR feeding back the motor-side encoders) with quasi-static series
    elasticity runs to the end (it was an algebraic loop), one plan."""
    stiffness = "plant: {effects: {joint_stiffness_Nm_rad: [1.0e+4, 1.0e+4, 1.0e+4, 1.0e+4, 4.0e+3, 4.0e+3, 4.0e+3]}}"
    args = ["--scenario-text", stiffness, "--scenario-text", "planner: {num_plans: 1}"]
    assert main(["run", str(SCENARIOS_DIR / "quickstart.yaml"), "--out", str(tmp_path), *args]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["success"] and summary["collisions"] == 0


def _feedback_run(robot, effects):
    """0.03 s of the arm (no payload, noisy sensor, fixed seed) under u = g(q0) - 5 v + 20 (q0 - q)
    + 3 sin(30 t): logs (measured torque, state, (motor, applied torque, plant state)), one row per step."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import BasicVector, LeafSystem
    from pydrake.systems.primitives import VectorLogSink
    from safesysid.systems.controller.armour import ControllerDynamics

    s = load_scenario(overrides={"payload": {"dumbbell": "none"}, "plant": {"effects": effects}})
    q0 = np.asarray(s.q0_rad, float)
    hold = ControllerDynamics(robot).gravity(q0, robot.theta)

    class Feedback(LeafSystem):
        def __init__(self):
            super().__init__()
            self.state = self.DeclareVectorInputPort("state", 14)
            self.DeclareVectorOutputPort("u", BasicVector(7), self._calc)

        def _calc(self, context, out):
            x = self.state.Eval(context)
            out.SetFromVector(hold - 5.0 * x[7:] + 20.0 * (q0 - x[:7]) + 3.0 * np.sin(30.0 * context.get_time()))

    b = DiagramBuilder()
    arm = add_real_arm(b, s, robot=robot)
    law = b.AddSystem(Feedback())
    b.Connect(arm.state_output, law.state)
    b.Connect(law.get_output_port(), arm.commanded_torque_input)
    ports = (arm.measured_torque_output, arm.state_output, arm.motor_torque_output, arm.applied_torque_output)
    ports += (arm.plant_state_output,)
    sinks = [b.AddSystem(VectorLogSink(p.size(), 0.001)) for p in ports]
    for port, sink in zip(ports, sinks):
        b.Connect(port, sink.get_input_port())
    sim = Simulator(b.Build())
    arm.set_state(sim.get_mutable_context(), q0)
    arm.seed_noise(sim.get_mutable_context())  # the same noise in every run
    sim.AdvanceTo(0.03)
    measured, state, motor, applied, plant_state = (k.FindLog(sim.get_context()).data().T for k in sinks)
    return measured, state, (motor, applied, plant_state)
