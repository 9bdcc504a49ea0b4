"""Effects of the simulated arm that the diagnosis names but the robot model has no term for:
load-dependent friction mu |tau| sgn v and Stribeck friction Fs sgn v exp(-(v/vs)^2), both in the
diagnosis' law (systems/dg.py), and a late torque reading, as plant.effects of the real arm."""

import numpy as np
import pytest
from helpers import FULL
from pydrake.systems.framework import DiagramBuilder
from safesysid.scenario import ScenarioError, load_scenario, robot_from_scenario
from safesysid.systems import diagnosis as dg
from safesysid.systems.real_arm import add_real_arm
from safesysid.systems.regressors import coulomb_shape, friction_columns

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
    law = friction_columns(v[None], np.zeros((1, 7)), "standard", robot.coulomb_smoothing)[0] @ robot.theta[70:]
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
    """torque_sensor_delay_s: the measured torque is the reading of d earlier (zero before);
    the motion is unchanged."""
    for delay in (0.001, 0.004):
        _late_reading(robot, delay)


def _late_reading(robot, delay):
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.primitives import ConstantVectorSource, VectorLogSink

    runs = {}
    steps = int(round(delay / 0.001))
    for name, d in (("late", delay), ("plain", 0.0)):
        # Noise-free: the noise source is a discrete state of its own, one step apart from the
        # torque path (real_arm.py); the torque path is what a late reading delays.
        s = load_scenario(
            overrides={
                "payload": {"dumbbell": "none"},
                "noise": {"distribution": "none"},
                "plant": {"effects": {"torque_sensor_delay_s": d}},
            }
        )
        b = DiagramBuilder()
        arm = add_real_arm(b, s, robot=robot)
        src = b.AddSystem(ConstantVectorSource(np.linspace(-3.0, 3.0, 7)))
        b.Connect(src.get_output_port(), arm.commanded_torque_input)
        sinks = [b.AddSystem(VectorLogSink(p.size(), 0.001)) for p in (arm.measured_torque_output, arm.state_output)]
        b.Connect(arm.measured_torque_output, sinks[0].get_input_port())
        b.Connect(arm.state_output, sinks[1].get_input_port())
        sim = Simulator(b.Build())
        arm.set_state(sim.get_mutable_context(), s.q0_rad)
        arm.seed_noise(sim.get_mutable_context())  # the same noise in both runs
        sim.AdvanceTo(0.02)
        runs[name] = [k.FindLog(sim.get_context()).data().T for k in sinks]
    (late, x_late), (plain, x_plain) = runs["late"], runs["plain"]
    np.testing.assert_array_equal(late[steps:], plain[:-steps])
    assert np.all(late[:steps] == 0)
    np.testing.assert_array_equal(x_late, x_plain)
