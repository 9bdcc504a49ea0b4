import numpy as np
from pydrake.geometry import Box
from pydrake.math import RigidTransform
from pydrake.multibody.plant import CoulombFriction
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource
from safesysid.systems.model.robot_model import load_robot, make_plant
from safesysid.systems.planner import reachability as reach
from safesysid.systems.plant.safety_monitor import SafetyMonitor, limit_ratio


def run_with_box(box_center, command=None, size=(0.1, 0.1, 0.1), name="box", q=None):
    robot = load_robot()
    builder = DiagramBuilder()
    plant, sg, _ = make_plant(robot.source, time_step=0.001, builder=builder)
    plant.RegisterCollisionGeometry(
        plant.world_body(), RigidTransform(box_center), Box(*size), name, CoulombFriction(0.5, 0.5)
    )
    plant.Finalize()
    monitor = builder.AddSystem(SafetyMonitor(plant, sg, robot, period_s=0.001))
    zero = builder.AddSystem(ConstantVectorSource(np.zeros(robot.n)))
    builder.Connect(zero.get_output_port(), plant.get_actuation_input_port())
    builder.Connect(sg.get_query_output_port(), monitor.query_port)
    builder.Connect(plant.get_state_output_port(), monitor.state_port)
    builder.Connect(zero.get_output_port(), monitor.torque_port)
    commanded = builder.AddSystem(ConstantVectorSource(np.zeros(robot.n) if command is None else command))
    builder.Connect(commanded.get_output_port(), monitor.command_port)
    diagram = builder.Build()
    sim = Simulator(diagram)
    ctx = plant.GetMyContextFromRoot(sim.get_mutable_context())
    plant.SetPositions(ctx, np.zeros(robot.n) if q is None else q)
    sim.Initialize()
    sim.AdvanceTo(0.001)  # the sample at t = 0 is taken as time moves past it
    record = monitor.record(monitor.GetMyContextFromRoot(sim.get_context()))
    assert record.times == [0.0]
    return record, plant, ctx


def test_box_on_the_gripper_is_a_collision():
    robot = load_robot()
    plant_tip = robot.forward_kinematics(np.zeros(robot.n))
    ee = plant_tip.p[0, robot.end_effector] + plant_tip.R[0, robot.end_effector] @ [0, 0, -0.15]
    record, _, _ = run_with_box(ee)
    summary = record.summary()
    assert summary["collisions"] == 1 and summary["min_clearance_m"] < -0.02
    far, _, _ = run_with_box(ee + [0.0, 0.6, 0.0])
    assert far.summary()["collisions"] == 0 and far.summary()["min_clearance_m"] > 0.2


def test_the_referee_measures_the_link_shapes_not_the_planner_spheres():
    """A box 5 cm from the half_arm_1 capsule (link shape): the referee reports 5 cm, where the
    planner's spheres (1.5 cm fatter) would report less than 4 cm."""
    robot = load_robot()
    kin = robot.forward_kinematics(np.zeros(robot.n))
    start, end = kin.p[0, 1], kin.p[0, 2]  # half_arm_1 capsule: its origin to joint 3
    mid = 0.5 * (start + end)
    side = np.cross(end - start, [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    centre = mid + side * (0.045 + 0.05 + 0.01)  # capsule radius, gap, half the 2 cm cube
    record, _, _ = run_with_box(centre, size=(0.02, 0.02, 0.02))
    clearance = record.summary()["min_clearance_m"]
    spheres = reach.arm_spheres(robot)
    c, _ = reach.sphere_centres(robot.tree, spheres, np.zeros((1, robot.n)), with_jacobian=False)
    sd, _ = reach.box_signed_distance(
        c[0],
        np.broadcast_to(centre, c[0].shape),
        np.broadcast_to(np.eye(3), (len(spheres), 3, 3)),
        np.full(c[0].shape, 0.01),
    )
    print(f"referee {clearance:.4f} m, planner spheres {np.min(sd - spheres.radius):.4f} m")
    assert abs(clearance - 0.05) < 5e-4 and np.min(sd - spheres.radius) < 0.04


def test_a_box_through_the_fixed_base_is_a_collision_but_the_floor_it_stands_on_is_not():
    """SceneGraph filters the welded base's pairs with the world; the referee queries them."""
    record, _, _ = run_with_box([-0.05, 0.0, 0.08], size=(0.05, 0.3, 0.05))  # 2 cm into the base, below the shoulder
    summary = record.summary()
    assert summary["collisions"] == 1 and abs(summary["min_clearance_m"] + 0.02) < 1e-6, summary
    assert record.closest_pair[0][0].endswith("base_link_capsule")
    floor, _, _ = run_with_box([0.0, 0.0, -0.025], size=(4.0, 4.0, 0.05), name="floor")
    assert floor.summary()["collisions"] == 0 and floor.summary()["min_clearance_m"] > 0.05


def test_limit_ratio():
    lower = np.array([-np.inf, -2.0])
    upper = np.array([np.inf, 2.0])
    assert np.allclose(limit_ratio(np.array([[5.0, 1.0], [0, -2.0]]), lower, upper), [0.5, 1.0])


def test_the_command_before_saturation_is_judged():
    """A command beyond the limit is recorded as such even when the torque applied is zero."""
    robot = load_robot()
    command = np.zeros(robot.n)
    command[6] = -1.5 * robot.joint_params.torque_limit[6]
    record, _, _ = run_with_box([2.0, 0.0, 0.0], command)
    summary = record.summary()
    assert summary["max_commanded_torque_ratio"] == 1.5 and summary["max_torque_ratio"] == 0.0


def test_two_contexts_keep_their_own_record():
    """The record is state in the Context: two simulations of ONE diagram, the arm at different
    poses, advanced alternately, record what each records alone."""
    robot = load_robot()
    builder = DiagramBuilder()
    plant, sg, _ = make_plant(robot.source, time_step=0.001, builder=builder)
    plant.RegisterCollisionGeometry(
        plant.world_body(), RigidTransform([0.6, 0.0, 0.3]), Box(0.1, 0.1, 0.1), "box", CoulombFriction(0.5, 0.5)
    )
    plant.Finalize()
    monitor = builder.AddSystem(SafetyMonitor(plant, sg, robot, period_s=0.001))
    zero = builder.AddSystem(ConstantVectorSource(np.zeros(robot.n)))
    builder.Connect(zero.get_output_port(), plant.get_actuation_input_port())
    for source, port in (
        (sg.get_query_output_port(), monitor.query_port),
        (plant.get_state_output_port(), monitor.state_port),
        (zero.get_output_port(), monitor.torque_port),
        (zero.get_output_port(), monitor.command_port),
    ):
        builder.Connect(source, port)
    diagram = builder.Build()

    def start(q):
        sim = Simulator(diagram)
        plant.SetPositions(plant.GetMyMutableContextFromRoot(sim.get_mutable_context()), q)
        sim.Initialize()
        return sim

    def record(sim):
        return monitor.record(monitor.GetMyContextFromRoot(sim.get_context()))

    poses = (np.zeros(robot.n), np.full(robot.n, 0.3))
    together = [start(q) for q in poses]
    for stop in (0.0055, 0.0105):
        for sim in together:
            sim.AdvanceTo(stop)
    for sim, q in zip(together, poses):
        alone = start(q)
        for stop in (0.0055, 0.0105):
            alone.AdvanceTo(stop)
        assert len(record(sim).times) == 11 and record(sim) == record(alone)
    assert record(together[0]).clearance != record(together[1]).clearance


def test_judging_the_log_afterwards_gives_the_in_loop_record():
    """arm-sim's referee judges its log after the run (judge_log): sample for sample the record of
    the same monitor in the loop, on experiment_a's station (an obstacle 4 cm from the arm)."""
    from pydrake.systems.primitives import LogVectorOutput
    from safesysid.scenario import load_scenario
    from safesysid.systems.plant.safety_monitor import judge_log
    from safesysid.systems.plant.station import add_real_arm

    scenario = load_scenario("scenarios/experiment_a.yaml")
    builder = DiagramBuilder()
    arm = add_real_arm(builder, scenario, seed=0)
    h = scenario.plant.time_step_s
    monitor = builder.AddSystem(SafetyMonitor(arm.plant, arm.scene_graph, arm.robot, period_s=h))
    torque = builder.AddSystem(ConstantVectorSource(np.linspace(-30.0, 30.0, arm.n)))  # falls and swings
    builder.Connect(torque.get_output_port(), arm.commanded_torque_input)
    ports = (arm.query_output, arm.plant_state_output, arm.motor_torque_output, torque.get_output_port())
    for output, port in zip(ports, (monitor.query_port, monitor.state_port, monitor.torque_port, monitor.command_port)):
        builder.Connect(output, port)
    logs = {
        key: LogVectorOutput(port, builder, h) for key, port in zip(("state", "motor_torque", "command"), ports[1:])
    }
    diagram = builder.Build()
    sim = Simulator(diagram)
    arm.set_state(sim.get_mutable_context(), np.asarray(scenario.q0_rad, float))
    sim.AdvanceTo(0.2 + 0.5 * h)
    ctx = sim.get_context()
    data = {key: log.FindLog(ctx).data().T for key, log in logs.items()}
    data["t"] = logs["command"].FindLog(ctx).sample_times()
    live = monitor.record(monitor.GetMyContextFromRoot(ctx))
    judged = judge_log(monitor, arm, diagram.CreateDefaultContext(), data)
    assert len(judged.times) == len(live.times) == 201
    for name in ("times", "clearance", "joint_ratio", "velocity_ratio", "torque_ratio", "commanded_ratio"):
        np.testing.assert_allclose(getattr(judged, name), getattr(live, name), rtol=0, atol=1e-12, err_msg=name)
    assert judged.closest_pair == live.closest_pair
    assert np.ptp(judged.clearance) > 1e-3  # the arm moved: the geometry is each sample's, not one pose's
