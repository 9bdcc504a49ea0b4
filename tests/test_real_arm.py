"""The real-arm block: true dynamics (armature, payload, friction law), saturation, torque
sensor noise, unmodelled effects, and obstacle geometry for signed-distance queries."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, VectorLogSink
from safesysid.scenario import load_scenario
from safesysid.systems.controller.armour import ControllerDynamics
from safesysid.systems.model.loading import robot_from_scenario
from safesysid.systems.model.regressors import friction_columns
from safesysid.systems.plant.arm_plant import scenario_dumbbell, true_theta
from safesysid.systems.plant.station import add_real_arm


@pytest.fixture(scope="module")
def robot():
    return robot_from_scenario(load_scenario())


def _rig(scenario, robot, torque, dumbbell="scenario", log_step=None):
    """Arm driven by a constant command; loggers on every output. Returns (sim, arm, logs)."""
    b = DiagramBuilder()
    arm = add_real_arm(b, scenario, robot=robot, dumbbell=dumbbell)
    src = b.AddSystem(ConstantVectorSource(np.asarray(torque, float)))
    b.Connect(src.get_output_port(), arm.commanded_torque_input)
    logs = {}
    for name, port in (
        ("state", arm.state_output),
        ("measured", arm.measured_torque_output),
        ("applied", arm.applied_torque_output),
        ("motor", arm.motor_torque_output),
    ):
        logs[name] = b.AddSystem(VectorLogSink(port.size(), log_step or scenario.plant.time_step_s))
        b.Connect(port, logs[name].get_input_port())
    sim = Simulator(b.Build())
    return sim, arm, logs


def _log(sim, sink):
    return sink.FindLog(sim.get_context()).data().T


def test_mass_matrix_is_rigid_plus_armature(robot):
    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}})
    sim, arm, _ = _rig(s, robot, np.zeros(7))
    ctx = sim.get_mutable_context()
    rng = np.random.default_rng(0)
    theta = true_theta(robot, scenario_dumbbell(s))
    no_armature = theta.copy()
    no_armature[10 * robot.n + 2 :: 4] = 0.0
    for _ in range(3):
        q = rng.uniform(-2, 2, 7)
        arm.set_state(ctx, q)
        m_plant = arm.plant.CalcMassMatrix(arm.plant_context(ctx))
        np.testing.assert_allclose(m_plant, robot.mass_matrix(q[None], theta)[0], atol=1e-12)
        np.testing.assert_allclose(
            m_plant - np.diag(robot.joint_params.armature), robot.mass_matrix(q[None], no_armature)[0], atol=1e-12
        )


@pytest.mark.parametrize("bell", ["none", "8lb"])
def test_holding_torque_keeps_the_arm_still(robot, bell):
    """u = g(q; theta_true) + beta holds the arm: the plant has exactly the model's gravity."""
    s = load_scenario(overrides={"payload": {"dumbbell": bell}, "noise": {"distribution": "none"}})
    q0 = np.array(s.q0_rad)
    hold = ControllerDynamics(robot).gravity(q0, true_theta(robot, scenario_dumbbell(s)))
    sim, arm, logs = _rig(s, robot, hold)
    arm.set_state(sim.get_mutable_context(), q0)
    sim.AdvanceTo(0.5)
    x = _log(sim, logs["state"])
    assert np.abs(x[:, :7] - q0).max() < 1e-8
    # The same torque without the payload's share lets the loaded arm sag: the payload is real.
    if bell != "none":
        wrong = ControllerDynamics(robot).gravity(q0, robot.theta)
        sim, arm, logs = _rig(s, robot, wrong)
        arm.set_state(sim.get_mutable_context(), q0)
        sim.AdvanceTo(0.5)
        assert np.abs(_log(sim, logs["state"])[-1, :7] - q0).max() > 1e-3


def test_grasp_and_release_change_the_dynamics(robot):
    s = load_scenario(overrides={"payload": {"dumbbell": "none"}})
    bell = scenario_dumbbell(load_scenario(overrides={"payload": {"dumbbell": "5lb"}}))
    sim, arm, _ = _rig(s, robot, np.zeros(7))
    ctx = sim.get_mutable_context()
    q = np.array(s.q0_rad)
    arm.set_state(ctx, q)
    dyn = ControllerDynamics(robot)
    g = lambda: -arm.plant.CalcGravityGeneralizedForces(arm.plant_context(ctx)) + robot.joint_params.offset  # noqa: E731
    np.testing.assert_allclose(g(), dyn.gravity(q, robot.theta), atol=1e-10)
    arm.set_payload(ctx, bell)
    np.testing.assert_allclose(g(), dyn.gravity(q, true_theta(robot, bell)), atol=1e-10)
    arm.set_payload(ctx, None)
    np.testing.assert_allclose(g(), dyn.gravity(q, robot.theta), atol=1e-10)


def test_friction_uses_the_regressor_law(robot):
    s = load_scenario()
    b = DiagramBuilder()
    add_real_arm(b, s, robot=robot)
    diagram = b.Build()
    friction = diagram.GetSubsystemByName("real_arm").GetSubsystemByName("joint_friction")
    ctx = friction.CreateDefaultContext()
    rng = np.random.default_rng(1)
    v = rng.normal(scale=0.02, size=7)  # around the smoothing velocity: tanh matters
    tau = rng.normal(size=7)
    friction.applied.FixValue(ctx, tau)
    friction.state.FixValue(ctx, np.concatenate([np.zeros(7), v]))
    law = (
        friction_columns(v[None], a=np.zeros((1, 7)), kind="standard", smoothing_velocity=robot.coulomb_smoothing)[0]
        @ robot.theta[70:]
    )
    np.testing.assert_allclose(friction.get_output_port().Eval(ctx), tau - law, atol=1e-12)
    assert robot.coulomb_smoothing == s.robot.coulomb_smoothing_rad_s > 0


def test_saturation_and_noisy_torque_sensor(robot):
    s = load_scenario(
        overrides={"noise": {"torque_ratio": 0.05, "torque_floor_Nm": 0.1}, "payload": {"dumbbell": "none"}}
    )
    command = np.array([500.0, -500.0, 10.0, -10.0, 100.0, 1.0, 0.0])
    sim, arm, logs = _rig(s, robot, command)
    arm.seed_noise(sim.get_mutable_context())
    arm.set_state(sim.get_mutable_context(), s.q0_rad)
    sim.AdvanceTo(0.3)
    limit = robot.joint_params.torque_limit
    # The only clamp is on the motor torque (friction acts after it, unclamped).
    assert all(np.isinf(arm.plant.get_joint_actuator(i).effort_limit()) for i in arm.plant.GetJointActuatorIndices())
    applied = _log(sim, logs["applied"])
    expected = np.clip(command, -limit, limit)
    np.testing.assert_allclose(applied, np.broadcast_to(expected, applied.shape))
    noise = _log(sim, logs["measured"]) - applied
    bound = 0.05 * np.abs(applied) + 0.1
    ratio = noise / bound
    assert np.all(np.abs(ratio) <= 1.0)
    assert np.abs(ratio).max() > 0.95 and abs(ratio.mean()) < 0.1  # uniform, filling the bound
    # Deterministic per seed (Drake's SetRandomContext through RealArm.seed_noise), new per seed.
    for seed, same in ((s.seed, True), (s.seed + 1, False)):
        sim2, arm2, logs2 = _rig(s, robot, command)
        arm2.seed_noise(sim2.get_mutable_context(), seed)
        arm2.set_state(sim2.get_mutable_context(), s.q0_rad)
        sim2.AdvanceTo(0.3)
        assert np.array_equal(_log(sim2, logs2["measured"]), _log(sim, logs["measured"])) == same


def test_sensor_offset_scale_and_delay(robot):
    eff = {"torque_sensor_offset_Nm": [0.5] * 7, "torque_sensor_scale": [1.1] * 7, "time_delay_s": 0.005}
    s = load_scenario(
        overrides={"noise": {"distribution": "none"}, "payload": {"dumbbell": "none"}, "plant": {"effects": eff}}
    )
    q0 = np.array(s.q0_rad)
    hold = ControllerDynamics(robot).gravity(q0, robot.theta)
    sim, arm, logs = _rig(s, robot, hold)
    arm.set_state(sim.get_mutable_context(), q0)
    sim.AdvanceTo(0.05)
    measured, motor, applied = (_log(sim, logs[k]) for k in ("measured", "motor", "applied"))
    np.testing.assert_allclose(measured, 1.1 * motor + 0.5)
    assert np.all(applied[:5] == 0) and np.allclose(applied[6:], hold)  # 5 steps late
    # Before the delayed torque arrives the arm falls a little: the delay is physical.
    assert np.abs(_log(sim, logs["state"])[-1, :7] - q0).max() > 1e-6


def test_lagged_torque_sensor(robot):
    """torque_sensor_lag_s low-passes the (noisy) sensor signal: it starts steady and follows
    y_k = a y_(k-1) + (1 - a) raw_(k-1), a = exp(-h/d), raw the same run's unlagged reading (the
    torque held over the step that ended: the exact lag of a held torque, no one-step lead); the
    motion is unchanged (a sensor effect only)."""
    d = 0.04
    s = load_scenario(
        overrides={
            "noise": {"torque_ratio": 0.02, "torque_floor_Nm": 0.05},
            "payload": {"dumbbell": "none"},
            "plant": {"effects": {"torque_sensor_lag_s": d}},
        }
    )
    plain = load_scenario(
        overrides={"noise": {"torque_ratio": 0.02, "torque_floor_Nm": 0.05}, "payload": {"dumbbell": "none"}}
    )
    q0 = np.array(s.q0_rad)
    hold = ControllerDynamics(robot).gravity(q0, robot.theta)
    runs = {}
    for name, scen in (("lag", s), ("plain", plain)):
        sim, arm, logs = _rig(scen, robot, hold)
        arm.seed_noise(sim.get_mutable_context())  # the same draws in both runs
        arm.set_state(sim.get_mutable_context(), q0)
        sim.AdvanceTo(0.1)
        runs[name] = {k: _log(sim, logs[k]) for k in ("measured", "state")}
    raw, lagged = runs["plain"]["measured"], runs["lag"]["measured"]
    a = np.exp(-s.plant.time_step_s / d)
    expected = np.empty_like(raw)
    expected[0] = raw[0]
    for k in range(1, len(raw)):
        expected[k] = a * expected[k - 1] + (1 - a) * raw[k - 1]
    np.testing.assert_allclose(lagged, expected, rtol=1e-12, atol=1e-12)
    assert np.abs(lagged - raw).max() > 0.01  # the noise is filtered (not vacuous)
    np.testing.assert_array_equal(runs["lag"]["state"], runs["plain"]["state"])


def test_base_tilt_changes_gravity(robot):
    s = load_scenario(
        overrides={
            "noise": {"distribution": "none"},
            "payload": {"dumbbell": "none"},
            "plant": {"effects": {"base_tilt_rad": [0.05, 0.0]}},
        }
    )
    q0 = np.array(s.q0_rad)
    sim, arm, _ = _rig(s, robot, np.zeros(7))
    g = arm.plant.gravity_field().gravity_vector()
    assert np.linalg.norm(g) == pytest.approx(9.81, rel=1e-3) and abs(g[1]) > 0.4
    ctx = sim.get_mutable_context()
    arm.set_state(ctx, q0)
    tilted = -arm.plant.CalcGravityGeneralizedForces(arm.plant_context(ctx))
    assert np.abs(tilted - ControllerDynamics(robot).gravity(q0, robot.theta)).max() > 0.1


def test_joint_elasticity_offsets_the_encoders(robot):
    stiffness = np.full(7, 2000.0)
    s = load_scenario(
        overrides={
            "noise": {"distribution": "none"},
            "payload": {"dumbbell": "none"},
            "plant": {"effects": {"joint_stiffness_Nm_rad": stiffness.tolist()}},
        }
    )
    q0 = np.array(s.q0_rad)
    hold = ControllerDynamics(robot).gravity(q0, robot.theta)
    sim, arm, logs = _rig(s, robot, hold)
    arm.set_state(sim.get_mutable_context(), q0)
    sim.AdvanceTo(0.1)
    x = _log(sim, logs["state"])
    true_q = arm.plant.GetPositions(arm.plant_context(sim.get_context()))
    np.testing.assert_allclose(true_q, q0, atol=1e-8)
    np.testing.assert_allclose(x[-1, :7], q0 + (hold - robot.joint_params.offset) / stiffness, atol=1e-8)


def _dynamic_elasticity(stiffness, damping=(), time_step=0.00025, **overrides):
    effects = {"joint_elasticity": "dynamic", "joint_stiffness_Nm_rad": [float(k) for k in stiffness]}
    if len(damping):
        effects["joint_damping_Nms_rad"] = [float(d) for d in damping]
    return load_scenario(
        overrides={
            "noise": {"distribution": "none"},
            "payload": {"dumbbell": "none"},
            "plant": {"time_step_s": time_step, "effects": effects},
            **overrides,
        }
    )


def test_dynamic_joint_elasticity_is_a_motor_and_a_spring(robot):
    """joint_elasticity: dynamic. The holding torque holds the arm from the first step (the springs
    start wound by the links' weight); after a torque step on joint 7 the plant's velocities follow
    the two-mass model integrated here independently, M dv = tau_s, B dw = step - friction(w) - tau_s,
    tau_s = K (theta_m - q) + D (w - v) (M: the link-side mass matrix, B: the armature; the damper's
    -D v on the link implicit, as the plant's joint damping), ringing where the rigid arm does not."""
    jp = robot.joint_params
    stiffness, damping = np.array([1e4] * 6 + [2000.0]), np.array([20.0] * 6 + [0.5])
    s = _dynamic_elasticity(stiffness, damping)
    h, q0 = s.plant.time_step_s, np.array(s.q0_rad)
    hold = ControllerDynamics(robot).gravity(q0, robot.theta) + jp.offset
    sim, arm, logs = _rig(s, robot, hold)
    ctx = sim.get_mutable_context()
    arm.set_state(ctx, q0)
    weight = -arm.plant.CalcGravityGeneralizedForces(arm.plant_context(ctx))[:7]
    motor = arm.transmission.GetMyContextFromRoot(ctx).get_discrete_state_vector().value()
    np.testing.assert_allclose(motor[:7], q0 + weight / stiffness, atol=1e-12)
    sim.AdvanceTo(0.2)
    np.testing.assert_allclose(_log(sim, logs["state"])[:, :7], np.tile(q0, (801, 1)), atol=1e-9)

    step = np.eye(7)[6]
    sim, arm, logs = _rig(s, robot, hold + step)
    arm.set_state(sim.get_mutable_context(), q0)
    mass = arm.plant.CalcMassMatrix(arm.plant_context(sim.get_context()))[:7, :7]
    sim.AdvanceTo(0.02)
    v_plant = _log(sim, logs["state"])[:, 7:]
    q, v, motor, w = (np.zeros(7) for _ in range(4))  # deviations from the equilibrium
    v_model = [v]
    for _ in range(len(v_plant) - 1):
        spring = stiffness * (motor - q) + damping * (w - v)
        friction = jp.coulomb * np.tanh(w / robot.coulomb_smoothing) + jp.viscous * w
        v_next = np.linalg.solve(mass + h * np.diag(damping), mass @ v + h * (stiffness * (motor - q) + damping * w))
        w = w + h * (step - friction - spring) / jp.armature
        v = v_next
        q = q + h * v
        motor = motor + h * w
        v_model.append(v)
    v_model = np.array(v_model)
    assert np.abs(v_plant - v_model).max() < 2e-5 * np.abs(v_model).max()  # 5.8e-4 with a one-step-late motor update
    rigid = load_scenario(overrides={"noise": {"distribution": "none"}, "payload": {"dumbbell": "none"}})
    sim, arm, logs = _rig(rigid, robot, hold + step)
    arm.set_state(sim.get_mutable_context(), q0)
    sim.AdvanceTo(0.02)
    v_rigid = _log(sim, logs["state"])[:, 13]
    assert np.abs(v_rigid - v_model[::4, 6][: len(v_rigid)]).max() > 0.02 * np.abs(v_model).max()


@pytest.mark.parametrize(
    "effects, message",
    [
        ({"joint_stiffness_Nm_rad": [1e4] * 7, "joint_elasticity": "dynamic"}, "too stiff for plant.time_step_s"),
        ({"joint_stiffness_Nm_rad": [1e4] * 7, "joint_elasticity": "wobbly"}, "joint_elasticity: 'wobbly'"),
        (
            {"joint_stiffness_Nm_rad": [1e4] * 7, "joint_damping_Nms_rad": [1.0] * 7},
            "only with joint_elasticity: dynamic",
        ),
        ({"joint_damping_Nms_rad": [1.0] * 7}, "needs joint_stiffness_Nm_rad"),
    ],
)
def test_joint_elasticity_options_are_checked(robot, effects, message):
    from safesysid.systems.config import ScenarioError

    s = load_scenario(overrides={"payload": {"dumbbell": "none"}, "plant": {"effects": effects}})
    with pytest.raises(ScenarioError, match=message):
        add_real_arm(DiagramBuilder(), s, robot=robot)


def test_velocity_noise_is_bounded_seeded_and_only_on_the_reading(robot):
    """plant.effects.velocity_noise_rad_s: the encoders' velocity = the plant's + uniform noise
    within the bound (reaching near it), positions exact; the same seed gives the same draws."""
    bound = 0.02
    s = load_scenario(
        overrides={"payload": {"dumbbell": "none"}, "plant": {"effects": {"velocity_noise_rad_s": bound}}}
    )
    q0 = np.array(s.q0_rad)
    hold = ControllerDynamics(robot).gravity(q0, robot.theta)
    readings = []
    for seed in (3, 3, 4):
        sim, arm, logs = _rig(s, robot, hold)
        arm.set_state(sim.get_mutable_context(), q0)
        arm.seed_noise(sim.get_mutable_context(), seed)
        sim.AdvanceTo(0.2)
        readings.append(_log(sim, logs["state"]))
    x = readings[0]
    q_true = arm.plant.GetPositions(arm.plant_context(sim.get_context()))
    np.testing.assert_allclose(x[-1, :7], q_true, atol=1e-4)  # the arm holds still: positions exact
    noise = x[:, 7:]  # the arm is (almost) at rest, so the reading is the noise
    assert np.abs(noise).max() <= bound + 1e-6 and np.abs(noise).max() > 0.9 * bound
    assert abs(noise.mean()) < 0.1 * bound
    np.testing.assert_array_equal(readings[0], readings[1])
    assert not np.array_equal(readings[0], readings[2])


def test_obstacles_and_floor_for_signed_distance(robot):
    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}})
    q0 = np.array(s.q0_rad)
    kin = robot.forward_kinematics(q0[None])
    ee_origin = kin.p[0, robot.end_effector]
    grasp = kin.R[0, robot.end_effector] @ robot.extra["grasp_point"] + ee_origin
    far = grasp + np.array([0.0, 0.0, 0.6])
    obstacles = [
        {"name": "on_payload", "xyz_m": grasp.tolist(), "size_m": [0.05, 0.05, 0.05]},
        {"name": "far", "xyz_m": far.tolist(), "size_m": [0.05, 0.05, 0.05]},
    ]
    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}, "obstacles": obstacles})
    sim, arm, _ = _rig(s, robot, np.zeros(7))
    ctx = sim.get_mutable_context()
    arm.set_state(ctx, q0)
    query = arm.scene_graph.get_query_output_port().Eval(arm.scene_graph.GetMyContextFromRoot(ctx))
    inspector = query.inspector()
    names = {inspector.GetName(g) for g in inspector.GetAllGeometryIds()}
    assert {"obstacle_0_on_payload", "obstacle_1_far", "floor"} <= names
    assert any("dumbbell_8lb_handle" in name for name in names)
    dist = {}
    for pair in query.ComputeSignedDistancePairwiseClosestPoints(2.0):
        for gid in (pair.id_A, pair.id_B):
            name = inspector.GetName(gid)
            if name.startswith("obstacle"):
                dist[name] = min(dist.get(name, np.inf), pair.distance)
    assert dist["obstacle_0_on_payload"] < 0 < dist["obstacle_1_far"]


def test_released_payload_stops_colliding(robot):
    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}})
    q0 = np.array(s.q0_rad)
    kin = robot.forward_kinematics(q0[None])
    grasp = kin.R[0, robot.end_effector] @ robot.extra["grasp_point"] + kin.p[0, robot.end_effector]
    s = load_scenario(
        overrides={
            "payload": {"dumbbell": "8lb"},
            "obstacles": [{"name": "at_grasp", "xyz_m": grasp.tolist(), "size_m": [0.03] * 3}],
        }
    )
    bell = scenario_dumbbell(s)
    sim, arm, _ = _rig(s, robot, ControllerDynamics(robot).gravity(q0, true_theta(robot, bell)))
    ctx = sim.get_mutable_context()
    arm.set_state(ctx, q0)

    def payload_pairs():
        sg_ctx = arm.scene_graph.GetMyContextFromRoot(ctx)
        query = arm.scene_graph.get_query_output_port().Eval(sg_ctx)
        names = [
            (query.inspector().GetName(p.id_A), query.inspector().GetName(p.id_B))
            for p in query.ComputeSignedDistancePairwiseClosestPoints(0.5)
        ]
        return [n for n in names if any("dumbbell" in x for x in n)]

    assert payload_pairs() and all(not ("dumbbell" in a and "dumbbell" in b) for a, b in payload_pairs())
    arm.set_payload(ctx, None)
    assert payload_pairs() == []
    arm.set_payload(ctx, bell)
    pairs = payload_pairs()
    assert pairs and all("obstacle" in a or "obstacle" in b or "floor" in a or "floor" in b for a, b in pairs)


# ---- the real arm's robot parameters (issue 11, item 5) and what its torque log means ---------------
def _drawn_arm(mode, seed, bell="8lb"):
    s = load_scenario(overrides={"plant": {"robot_parameters": mode}, "payload": {"dumbbell": bell}, "seed": seed})
    robot = robot_from_scenario(s)
    b = DiagramBuilder()
    arm = add_real_arm(b, s, robot=robot)
    return s, robot, arm, b.Build()


@pytest.mark.parametrize("mode", ["drawn", "corner"])
def test_drawn_robot_parameters_stay_in_the_box_and_are_what_the_plant_uses(mode):
    """plant.robot_parameters draws links, friction, armature and offsets inside the box the
    controller, planner and estimator assume (nominal +- max(ratio |nominal|, floor)), keeps every
    link physically consistent, and the Drake plant's mass matrix, gravity and friction are those
    of the drawn theta. (HEAD: the plant used the nominal parameters exactly.)"""
    from safesysid.systems.model import inertial
    from safesysid.systems.model.uncertainty import parameter_radius

    s, robot, arm, diagram = _drawn_arm(mode, seed=3)
    radius = parameter_radius(robot, s.noise.theta_r_ratio, s.noise.theta_r_ratio, floors=s.noise.theta_r_floor)
    dev = (arm.theta - robot.theta) / radius
    assert np.all(np.abs(dev) <= 1.0 + 1e-12)
    n = robot.n
    assert np.all(arm.theta[10 * n :] != robot.theta[10 * n :])  # every friction parameter moved, beta too
    if mode == "corner":
        assert np.all(np.isclose(np.abs(dev[10 * n :]), 1.0)) and np.mean(np.isclose(np.abs(dev), 1.0)) > 0.5
    for i in range(n):
        assert inertial.is_physically_consistent(arm.theta[10 * i : 10 * i + 10])
    ctx = diagram.CreateDefaultContext()
    theta = arm.true_theta()
    rng = np.random.default_rng(0)
    dyn = ControllerDynamics(robot)
    for _ in range(3):
        q = rng.uniform(-2, 2, n)
        arm.set_state(ctx, q)
        plant_ctx = arm.plant_context(ctx)
        np.testing.assert_allclose(
            arm.plant.CalcMassMatrix(plant_ctx), robot.mass_matrix(q[None], theta)[0], atol=1e-12
        )
        beta = theta[10 * n + 3 :: 4]
        np.testing.assert_allclose(
            -arm.plant.CalcGravityGeneralizedForces(plant_ctx) + beta, dyn.gravity(q, theta), atol=1e-10
        )
    friction = diagram.GetSubsystemByName("real_arm").GetSubsystemByName("joint_friction")
    fctx = friction.CreateDefaultContext()
    v = rng.normal(scale=0.3, size=n)
    friction.applied.FixValue(fctx, np.zeros(n))
    friction.state.FixValue(fctx, np.concatenate([np.zeros(n), v]))
    law = (
        friction_columns(v[None], a=np.zeros((1, n)), kind="standard", smoothing_velocity=robot.coulomb_smoothing)[0]
        @ arm.theta[10 * n :]
    )
    np.testing.assert_allclose(friction.get_output_port().Eval(fctx), -law, atol=1e-12)


def test_drawn_parameters_are_seeded():
    a = _drawn_arm("drawn", seed=5)[2].theta
    b = _drawn_arm("drawn", seed=5)[2].theta
    c = _drawn_arm("drawn", seed=6)[2].theta
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
    s, robot, arm, _ = _drawn_arm("nominal", seed=5)
    np.testing.assert_array_equal(arm.theta, robot.theta)


def test_logged_torque_is_the_torque_held_over_the_next_step(robot):
    """The sensor's sample at t_k is the torque the plant applies over [t_k, t_k+1] (noise off):
    measured == applied sample by sample, and in the momentum identity over 0.1 s segments the
    left sum of the logged torque (what the estimator integrates) leaves a residual well below
    the right sum (a log lagged by one step) and the trapezoid (the old rule)."""
    from pydrake.systems.framework import LeafSystem
    from safesysid.systems import estimation as E

    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}, "noise": {"distribution": "none"}})
    theta = true_theta(robot, scenario_dumbbell(s))
    q0 = np.array(s.q0_rad)
    hold = ControllerDynamics(robot).gravity(q0, theta)
    n = robot.n

    class Wobble(LeafSystem):
        def __init__(self):
            super().__init__()
            self.DeclareVectorOutputPort(
                "u", n, lambda ctx, out: out.SetFromVector(hold + 8.0 * np.sin(7.0 * ctx.get_time() + np.arange(n)))
            )

    b = DiagramBuilder()
    arm = add_real_arm(b, s, robot=robot)
    src = b.AddSystem(Wobble())
    b.Connect(src.get_output_port(), arm.commanded_torque_input)
    logs = {}
    for name, port in (
        ("state", arm.state_output),
        ("measured", arm.measured_torque_output),
        ("applied", arm.applied_torque_output),
    ):
        logs[name] = b.AddSystem(VectorLogSink(port.size(), s.plant.time_step_s))
        b.Connect(port, logs[name].get_input_port())
    sim = Simulator(b.Build())
    arm.set_state(sim.get_mutable_context(), q0)
    sim.AdvanceTo(0.6)
    t = logs["state"].FindLog(sim.get_context()).sample_times()
    x, tau, applied = (_log(sim, logs[k]) for k in ("state", "measured", "applied"))
    np.testing.assert_array_equal(tau, applied)
    bounds, _ = E.segment_bounds(t, 0.1, 0.05)
    rows = E.build_segment_rows(robot, t, x[:, :n], x[:, n:], tau, bounds, E.EstimatorSettings())
    lhs = rows.Y @ theta[robot.ee_slice] + np.einsum("snk,k->sn", rows.D_r, theta[robot.rest_mask()])
    left = np.abs(lhs - rows.T).max()
    right = np.abs(lhs - np.stack([tau[a + 1 : b + 1].T @ np.diff(t[a : b + 1]) for a, b in bounds])).max()
    trapezoid = np.abs(lhs - E.segment_sums(tau, t, bounds, integration="trapezoid")).max()
    print(f"momentum residual max: left sum {left:.3g}, trapezoid {trapezoid:.3g}, right sum {right:.3g} N·m·s")
    assert left < 0.5 * trapezoid < 0.5 * right
