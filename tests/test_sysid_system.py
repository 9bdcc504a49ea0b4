"""SysIdEstimator in a Drake diagram with a MultibodyPlant (continuous, integrated by Drake) driven
through a zero-order hold, as a digital controller drives the arm."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import Adder, ConstantVectorSource, MatrixGain, ZeroOrderHold
from safesysid.scenario import load_scenario
from safesysid.systems.estimation import EstimatorSettings
from safesysid.systems.estimation.system import SysIdEstimator
from safesysid.systems.model.robot_model import load_robot, make_plant


class ComputedTorque(LeafSystem):
    """τ = inverse dynamics of the plant at a_d + Kp(q_d − q) + Kd(v_d − v), q_d a sum of sines
    (an exciting open-ended motion; gains in acceleration units so the loop is not stiff)."""

    def __init__(self, plant, q0):
        super().__init__()
        self.plant = plant
        self.ctx = plant.CreateDefaultContext()
        n = plant.num_velocities()
        self.q0 = np.asarray(q0, float)
        self.n = n
        self.DeclareVectorInputPort("state", 2 * n)
        self.DeclareVectorOutputPort("torque", n, self._calc)

    def desired(self, t):
        w = 1.3 * (1 + 0.3 * np.arange(1, self.n + 1))
        phase = w * t + np.arange(1, self.n + 1)
        return self.q0 + 0.4 * np.sin(phase), 0.4 * w * np.cos(phase), -0.4 * w * w * np.sin(phase)

    def _calc(self, context, output):
        from pydrake.multibody.tree import MultibodyForces

        x = self.get_input_port(0).Eval(context)
        n = self.n
        self.plant.SetPositionsAndVelocities(self.ctx, x)
        qd, vd, ad = self.desired(context.get_time())
        a = ad + 100.0 * (qd - x[:n]) + 20.0 * (vd - x[n:])
        forces = MultibodyForces(self.plant)
        self.plant.CalcForceElementsContribution(self.ctx, forces)
        output.SetFromVector(self.plant.CalcInverseDynamics(self.ctx, a, forces))


@pytest.fixture(scope="module")
def rigid_robot():
    """The RobotModel of the bare URDF plant: no friction, no armature (what Drake simulates)."""
    robot = load_robot()
    theta = robot.theta.copy()
    theta[10 * robot.n :] = 0.0
    return robot.with_theta(theta)


def build(robot, update_period_s=1.0, duration_s=3.0, sensor_offset_Nm=0.0, stop_time_s=np.inf):
    """Plant <- ZOH(1 ms) <- computed torque; the estimator logs the controller's output at t_k,
    which is what the hold latches at t_k and applies over [t_k, t_k+1] (the hold's own output
    at t_k is still the previous sample: logging it would shift the log by one step)."""
    builder = DiagramBuilder()
    # No SceneGraph: no contact between links (rigid-body dynamics only, as the model assumes).
    plant, _, _ = make_plant(robot.source, time_step=0.0)
    if not plant.is_finalized():
        plant.Finalize()
    builder.AddSystem(plant)
    scenario = load_scenario()
    settings = EstimatorSettings.from_scenario(scenario)
    est = builder.AddSystem(
        SysIdEstimator(
            robot,
            settings=settings,
            sample_period_s=1e-3,
            update_period_s=update_period_s,
            prior=(np.array(scenario.initial_interval.lower), np.array(scenario.initial_interval.upper)),
            prior_nominal=np.array(scenario.initial_interval.nominal),
            stop_time_s=stop_time_s,
        )
    )
    q0 = np.array([0.0, 0.3, 0.0, 1.5, 0.0, 0.8, 0.0])
    ctrl = builder.AddSystem(ComputedTorque(plant, q0))
    builder.Connect(plant.get_state_output_port(), ctrl.get_input_port(0))
    hold = builder.AddSystem(ZeroOrderHold(1e-3, robot.n))
    builder.Connect(ctrl.get_output_port(0), hold.get_input_port())
    # Actuators may not be in joint order: u = Bᵀ τ (B a permutation for this arm).
    to_actuators = builder.AddSystem(MatrixGain(plant.MakeActuationMatrix().T))
    builder.Connect(hold.get_output_port(), to_actuators.get_input_port(0))
    builder.Connect(to_actuators.get_output_port(0), plant.get_actuation_input_port())
    builder.Connect(plant.get_state_output_port(), est.GetInputPort("state"))
    sensor = builder.AddSystem(Adder(2, robot.n))  # a sensor offset fault when != 0
    offset = builder.AddSystem(ConstantVectorSource(np.full(robot.n, sensor_offset_Nm)))
    builder.Connect(ctrl.get_output_port(0), sensor.get_input_port(0))
    builder.Connect(offset.get_output_port(), sensor.get_input_port(1))
    builder.Connect(sensor.get_output_port(), est.GetInputPort("measured_torque"))
    diagram = builder.Build()
    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    plant.SetPositions(plant.GetMyMutableContextFromRoot(ctx), ctrl.desired(0.0)[0])
    plant.SetVelocities(plant.GetMyMutableContextFromRoot(ctx), ctrl.desired(0.0)[1])
    sim.get_mutable_integrator().set_target_accuracy(1e-6)
    return sim, diagram, plant, est


def test_model_matches_plant(rigid_robot):
    builder = DiagramBuilder()
    plant, _, _ = make_plant(rigid_robot.source, time_step=0.0, builder=builder)
    plant.Finalize()
    ctx = plant.CreateDefaultContext()
    q = np.array([0.1, 0.4, -0.3, 1.2, 0.5, 0.7, -0.2])
    plant.SetPositions(ctx, q)
    assert np.allclose(plant.CalcMassMatrix(ctx), rigid_robot.mass_matrix(q)[0], atol=1e-10)


def test_estimator_system_in_a_diagram(rigid_robot):
    sim, diagram, plant, est = build(rigid_robot, update_period_s=1.0)
    ctx = sim.get_mutable_context()
    est_ctx = est.GetMyContextFromRoot(ctx)
    sim.Initialize()
    n, ee = rigid_robot.n, rigid_robot.ee_slice
    prior_lo = est.GetOutputPort("theta_lower").Eval(est_ctx)
    assert prior_lo.shape == (14 * n,)
    assert prior_lo[ee][0] == pytest.approx(1.2)  # Table II prior before the first update
    sim.AdvanceTo(3.0005)  # the event at t = 3 s is handled when time moves past it
    info = est.GetOutputPort("update_info").Eval(est_ctx)
    assert info[0] == 3 and info[3] == 1.0  # three updates at t = 1, 2, 3 s, consistent
    assert (
        est.GetOutputPort("consistent").Eval(est_ctx)[0] == 1.0
        and est.consistent(est_ctx)
        and est.events(est_ctx) == []
    )
    theta0 = est.GetOutputPort("theta0").Eval(est_ctx)
    lo = est.GetOutputPort("theta_lower").Eval(est_ctx)
    hi = est.GetOutputPort("theta_upper").Eval(est_ctx)
    truth = rigid_robot.theta_e
    assert np.all(lo[ee] <= truth) and np.all(truth <= hi[ee])
    assert abs(theta0[ee][0] - truth[0]) <= 0.02 * truth[0]
    assert hi[ee][0] - lo[ee][0] < 1.0  # much tighter than the 4 kg prior
    rest = rigid_robot.rest_mask()
    assert np.allclose(theta0[rest], rigid_robot.theta[rest])
    hist = est.history(est_ctx)
    assert [round(h["t"], 6) for h in hist] == [1.0, 2.0, 3.0]
    assert all(h["update_time_s"] > 0 for h in hist)
    assert len(est.update_times_s(est_ctx)) == 3
    th_e0, lo_e, hi_e = est.final_estimate(est_ctx)
    assert np.allclose(lo_e, lo[ee])
    # A re-initialised simulation starts from the prior again.
    ctx.SetTime(0.0)
    sim.Initialize()
    assert est.GetOutputPort("update_info").Eval(est_ctx)[0] == 0


def test_estimator_stops_at_its_stop_time(rigid_robot):
    """stop_time_s (the task phase's switch): no sample after it is collected and no update runs,
    so the published box stays the one of the last update before it."""
    sim, diagram, plant, est = build(rigid_robot, update_period_s=1.0, stop_time_s=1.5)
    ctx = sim.get_mutable_context()
    est_ctx = est.GetMyContextFromRoot(ctx)
    sim.Initialize()
    sim.AdvanceTo(3.0005)
    assert [round(h["t"], 6) for h in est.history(est_ctx)] == [1.0]
    run = est._get(est_ctx)
    assert run.samples and max(row[0] for row in run.samples) <= 1.5 + 1e-9
    assert est.GetOutputPort("update_info").Eval(est_ctx)[0] == 1


def test_consistent_port_latches_off_and_the_box_is_kept(rigid_robot):
    """The torque sensor reads 1 N·m high on every joint (outside the declared bound): the estimator's
    `consistent` port drops to 0, an "inconsistent_estimate" event is recorded, and the published
    box never widens and stays inside the prior."""
    sim, diagram, plant, est = build(rigid_robot, update_period_s=1.0, sensor_offset_Nm=1.0)
    ctx = sim.get_mutable_context()
    est_ctx = est.GetMyContextFromRoot(ctx)
    sim.Initialize()
    ee = rigid_robot.ee_slice
    boxes = [(est.GetOutputPort("theta_lower").Eval(est_ctx)[ee], est.GetOutputPort("theta_upper").Eval(est_ctx)[ee])]
    for stop in (1.0005, 2.0005, 3.0005):
        sim.AdvanceTo(stop)
        boxes.append(
            (est.GetOutputPort("theta_lower").Eval(est_ctx)[ee], est.GetOutputPort("theta_upper").Eval(est_ctx)[ee])
        )
    for (lo0, hi0), (lo1, hi1) in zip(boxes, boxes[1:]):
        assert np.all(lo1 >= lo0) and np.all(hi1 <= hi0)
    assert est.GetOutputPort("consistent").Eval(est_ctx)[0] == 0.0 and not est.consistent(est_ctx)
    events = est.events(est_ctx)
    assert [e["kind"] for e in events if e["kind"] == "inconsistent_estimate"] == ["inconsistent_estimate"]
    assert "inconsistent" in events[0]["detail"]


def test_samples_are_what_the_discrete_arm_applies():
    """On the discrete real arm, the estimator's sample at t_k must be (x_k, τ_k) with τ_k the
    torque the plant applies over [t_k, t_k+1] — what the loggers record (tests/test_real_arm.py
    checks that pairing against the momentum identity). A time-varying state-feedback command
    makes any shift visible: sampled by a discrete update, the estimator read x_k+1 (the plant's
    state is already advanced) with the command of t_k."""
    from pydrake.systems.primitives import VectorLogSink
    from safesysid.online import make_estimator_system
    from safesysid.systems.controller.armour import ControllerDynamics
    from safesysid.systems.model.loading import robot_from_scenario
    from safesysid.systems.plant.station import add_real_arm

    s = load_scenario(overrides={"payload": {"dumbbell": "none"}})
    robot = robot_from_scenario(s)
    n = robot.n
    q0 = np.array(s.q0_rad)
    hold = ControllerDynamics(robot).gravity(q0, robot.theta)

    class Feedback(LeafSystem):
        def __init__(self):
            super().__init__()
            self.x = self.DeclareVectorInputPort("x", 2 * n)
            self.DeclareVectorOutputPort("u", n, self._calc)

        def _calc(self, ctx, out):
            x = self.x.Eval(ctx)
            t = ctx.get_time()
            out.SetFromVector(hold + 200.0 * (q0 + 0.05 * np.sin(9.0 * t) - x[:n]) - 20.0 * x[n:])

    b = DiagramBuilder()
    arm = add_real_arm(b, s, robot=robot)
    ctrl = b.AddSystem(Feedback())
    b.Connect(arm.state_output, ctrl.x)
    b.Connect(ctrl.get_output_port(), arm.commanded_torque_input)
    est = b.AddSystem(make_estimator_system(robot, s, update_period_s=10.0))
    b.Connect(arm.state_output, est.GetInputPort("state"))
    b.Connect(arm.measured_torque_output, est.GetInputPort("measured_torque"))
    logs = {
        name: b.AddSystem(VectorLogSink(port.size(), s.plant.time_step_s))
        for name, port in (("state", arm.state_output), ("torque", arm.measured_torque_output))
    }
    b.Connect(arm.state_output, logs["state"].get_input_port())
    b.Connect(arm.measured_torque_output, logs["torque"].get_input_port())
    sim = Simulator(b.Build())
    arm.set_state(sim.get_mutable_context(), q0)
    sim.Initialize()
    sim.AdvanceTo(0.05)
    samples = est.samples(est.GetMyContextFromRoot(sim.get_context()))
    t = logs["state"].FindLog(sim.get_context()).sample_times()
    x = logs["state"].FindLog(sim.get_context()).data().T
    tau = logs["torque"].FindLog(sim.get_context()).data().T
    k = np.rint(samples[:, 0] / s.plant.time_step_s).astype(int)
    assert len(k) >= 50 and np.allclose(t[k], samples[:, 0])
    np.testing.assert_array_equal(samples[:, 1 : 1 + 2 * n], x[k])
    np.testing.assert_array_equal(samples[:, 1 + 2 * n :], tau[k])


def test_two_contexts_of_one_diagram_do_not_share_run_data(rigid_robot):
    """The samples, the estimator and the history live in the Context: two simulations of ONE
    diagram advanced alternately give exactly what each gives alone (with the run data on the
    system object they would feed each other's samples to one estimator)."""
    sim_a, diagram, plant, est = build(rigid_robot, update_period_s=1.0)
    x0 = plant.GetPositionsAndVelocities(plant.GetMyContextFromRoot(sim_a.get_context())).copy()

    def start(sim, shift):
        ctx = plant.GetMyMutableContextFromRoot(sim.get_mutable_context())
        plant.SetPositionsAndVelocities(
            ctx, x0 + np.r_[np.full(plant.num_positions(), shift), np.zeros(plant.num_velocities())]
        )
        sim.get_mutable_integrator().set_target_accuracy(1e-6)
        sim.Initialize()
        return sim

    def result(sim):
        ctx = est.GetMyContextFromRoot(sim.get_context())
        return est.history(ctx), est.GetOutputPort("theta_lower").Eval(ctx), est.GetOutputPort("theta_upper").Eval(ctx)

    sims = [start(sim_a, 0.0), start(Simulator(diagram), 0.05)]
    for stop in (1.0005, 2.0005):
        for sim in sims:
            sim.AdvanceTo(stop)
    together = [result(sim) for sim in sims]
    for shift, (history, lo, hi) in zip((0.0, 0.05), together):
        alone = start(Simulator(diagram), shift)
        for stop in (1.0005, 2.0005):  # the same stops: they shape the integrator's steps
            alone.AdvanceTo(stop)
        history_alone, lo_alone, hi_alone = result(alone)
        assert [h["t"] for h in history] == [h["t"] for h in history_alone] and len(history) == 2
        assert [h["lower"] for h in history] == [h["lower"] for h in history_alone]
        np.testing.assert_array_equal(lo, lo_alone)
        np.testing.assert_array_equal(hi, hi_alone)
    assert together[0][0][-1]["lower"] != together[1][0][-1]["lower"]  # the two runs did differ
