"""The robot as the world sees it: a discrete MultibodyPlant with the true payload, friction,
armature, saturation, a noisy torque sensor, encoders and optional unmodelled effects.

Signal path (everything from the scenario and the RobotModel; nothing hard-coded):

    commanded torque u -> Saturation(+-torque_limit)  = motor torque tau_m   -> TorqueSensor
                       -> [StepDelay d]                = applied torque tau_a
                       -> JointFriction: tau_a - (Fc tanh(v/vs) + Fv v + beta)  -> plant actuation
    plant state (q, v) -> [SeriesElasticEncoders]      -> state output
    (dynamic elasticity: JointFriction at the motor's velocity -> ElasticTransmission -> plant)

- Armature Ia: each JointActuator gets rotor inertia Ia and gear ratio 1, so Drake adds the
  reflected inertia Ia to the mass-matrix diagonal (M_plant = M_rigid + diag(Ia), tested).
- Friction uses the regressors' law (vs = robot.coulomb_smoothing), evaluated explicitly at the
  step's velocity (stable by far at 1 kHz: h Fv / Ia ~ 1e-3).
- Payload: a body welded at robot.extra["grasp_point"] on the end-effector link, dumbbell
  shaped (handle cylinder along the end-effector x, two head cylinders; visual + collision).
  `RealArm.set_payload(context, dumbbell | None)` grasps or releases it at run time by setting
  the body's spatial inertia in the context; a released payload is massless and loses its
  collision role in the context (the shape stays the one the arm was built with; visual stays).
- Release onto a platform (`releasable=True`, the task phase of app/online.py): a second,
  free body "released_payload" with the same shape and inertia waits locked far below the floor;
  `RealArm.release(context)` hands the welded payload's pose and spatial velocity to it, unlocks
  it and empties the welded one (set_payload(None)), so the identification phase runs on exactly
  the welded dynamics and the released dumbbell falls and settles under Drake contact.
- Torque sensor: tau_meas = scale * (tau_m + n) + offset, n uniform in +-(ratio |tau_m| + floor)
  per sample and joint (noise.distribution "none": n = 0); scale = 1, offset = 0 by default. The
  draws come from a Drake RandomSource inside the station: seed them per context with
  RealArm.seed_noise(root_context, seed) (SetRandomContext with RandomGenerator(seed)).

Robot parameters (scenario.plant.robot_parameters: nominal, drawn or corner inside the declared
box) and the plant's scene: systems/plant/arm_plant.py; the fault stages: systems/plant/faults.py.

Unmodelled effects (scenario.plant.effects, each off by default):
- torque_sensor_offset_Nm / torque_sensor_scale: per joint, on the measured torque only.
- torque_sensor_lag_s: the sensor signal is low-passed (first order, time constant d), as a
  filtered torque signal is logged (safesysid diagnose finds d ~ 0.1 s on the real Gen3 logs).
- time_delay_s: the motor torque reaches the joint d seconds late (rounded to whole steps); the
  sensor reports the motor torque when it is produced, so logs show torque leading motion by d.
- torque_sensor_delay_s: the sensor reading arrives d seconds late (rounded to whole steps; zero
  before the first one): logs show torque lagging the motion by d (the diagnosis' pure delay
  with d > 0).
- base_tilt_rad [roll, pitch]: the base is tilted in the world, i.e. gravity in the base frame is
  R(roll, pitch)^T [0, 0, -g].
- load_friction_mu: friction that grows with the transmitted torque (gear teeth, harmonic
  drives), mu |tau_a| sgn v with tau_a the applied motor torque, which the sensor measures: the
  diagnosis' load_friction law tau_meas = tau_model + mu |tau_meas| sgn v.
- stribeck_friction_Nm / stribeck_velocity_rad_s: Fs sgn v exp(-(v/vs)^2) (diagnosis' law).
  Both use the model's Coulomb shape for sgn v (tanh(v/vs_c) with the scenario's smoothing).
- joint_stiffness_Nm_rad: series elasticity, quasi-static approximation: the link is driven as
  if rigid, but encoders sit on the motor side and read q + tau_s / K, tau_s = the torque the
  transmission carries (applied torque minus friction). Velocities are reported unchanged. This
  captures the torque-proportional position offset of a stiff gearbox, not its resonance.
  With joint_elasticity: dynamic (and joint_damping_Nms_rad) it is the flexible-joint model
  instead (ElasticTransmission): the armature becomes a motor of its own, driven by the applied
  torque against its friction, and a spring-damper carries the torque to the link; encoders and
  the referee read the link, the torque sensor still the motor torque. The springs are explicit:
  stiff ones need a small plant.time_step_s (checked at build, _check_elastic_step).
- velocity_noise_rad_s: the encoders' velocities carry uniform noise in +-bound per joint and
  step (a Drake RandomSource seeded with the others), seen by controller and estimator.
"""

from __future__ import annotations

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.geometry import CollisionFilterDeclaration, ProximityProperties
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.framework import BasicVector, Context, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import RandomSource, Saturation
from safesysid.systems.config import Scenario, ScenarioError
from safesysid.systems.model.loading import robot_from_scenario
from safesysid.systems.model.payload import Dumbbell
from safesysid.systems.model.robot_defaults import PER_JOINT, fill_robot_defaults
from safesysid.systems.model.robot_model import RobotModel
from safesysid.systems.plant import faults
from safesysid.systems.plant.arm_plant import (  # re-exported: callers import them from here
    _PARKED,
    RealArm,
    _dumbbell_spatial_inertia,
    _make_real_plant,
    _register_dumbbell_geometry,
    _register_obstacles,
    draw_robot_theta,
    real_robot_theta,
    scenario_dumbbell,
    true_theta,
)

__all__ = [
    "JointFriction",
    "RealArm",
    "SeriesElasticEncoders",
    "TorqueSensor",
    "add_real_arm",
    "draw_robot_theta",
    "real_robot_theta",
    "scenario_dumbbell",
    "true_theta",
]


class JointFriction(LeafSystem):
    """Generalized force on the joints: applied torque minus joint friction (the model's law
    Fc tanh(v / vs) + Fv v + beta, sign(v) when vs = 0; plus plant.effects' load-dependent
    mu |tau| and Stribeck Fs exp(-(v / vs_s)^2) terms with the same sign law)."""

    def __init__(self, coulomb, viscous, offset, smoothing, load_mu=0.0, stribeck=0.0, stribeck_vs=1.0):
        super().__init__()
        self.coulomb, self.viscous, self.offset = (np.asarray(x, float) for x in (coulomb, viscous, offset))
        self.smoothing = float(smoothing)
        self.load_mu, self.stribeck = np.asarray(load_mu, float), np.asarray(stribeck, float)
        self.stribeck_vs = float(stribeck_vs)
        n = self.n = len(self.coulomb)
        self.applied = self.DeclareVectorInputPort("applied_torque", n)
        self.state = self.DeclareVectorInputPort("state", 2 * n)
        self.DeclareVectorOutputPort(
            "actuation", BasicVector(n), self._calc, prerequisites_of_calc={self.all_input_ports_ticket()}
        )

    def _calc(self, context, output):
        v = self.state.Eval(context)[self.n :]
        law = np.tanh(v / self.smoothing) if self.smoothing > 0 else np.sign(v)
        applied = self.applied.Eval(context)
        extra = (self.load_mu * np.abs(applied) + self.stribeck * np.exp(-((v / self.stribeck_vs) ** 2))) * law
        output.SetFromVector(applied - (self.coulomb * law + self.viscous * v + self.offset) - extra)


class SeriesElasticEncoders(LeafSystem):
    """Motor-side encoders: q + tau_s / K (quasi-static series elasticity), v unchanged."""

    def __init__(self, stiffness):
        super().__init__()
        self.stiffness = np.asarray(stiffness, float)
        n = self.n = len(self.stiffness)
        self.state = self.DeclareVectorInputPort("state", 2 * n)
        self.transmitted = self.DeclareVectorInputPort("transmitted_torque", n)
        self.DeclareVectorOutputPort("measured_state", BasicVector(2 * n), self._calc)

    def _calc(self, context, output):
        x = self.state.Eval(context).copy()
        x[: self.n] += self.transmitted.Eval(context) / self.stiffness
        output.SetFromVector(x)


class ElasticTransmission(LeafSystem):
    """Series-elastic joints, dynamically (Spong's flexible-joint model): per joint a motor of
    inertia B (the armature) drives the link through a spring K and a damper D,

        B w_m' = drive - tau_s,   tau_s = K (theta_m - q) + D (w_m - v),   M(q) v' + C + g = tau_s,

    drive = applied torque minus the friction at the motor's velocity (JointFriction fed with
    `motor_state`). Discrete state (theta_m, w_m), symplectic Euler at the plant's step, in step
    with the plant's own update: both are unrestricted updates, so both read the state at the
    start of the step (a discrete update would run after the plant stepped). The damper's
    -D v on the link is the plant's joint damping (implicit in Drake's discrete solver: a light
    link would make it unstable here), so `link_actuation` = K (theta_m - q) + D w_m."""

    def __init__(self, stiffness, damping, inertia, time_step):
        super().__init__()
        self.stiffness, self.damping, self.inertia = (np.asarray(x, float) for x in (stiffness, damping, inertia))
        n = self.n = len(self.stiffness)
        self.h = float(time_step)
        self.drive = self.DeclareVectorInputPort("drive", n)
        self.link_state = self.DeclareVectorInputPort("link_state", 2 * n)
        self._motor = motor = self.DeclareDiscreteState(2 * n)
        self.DeclarePeriodicUnrestrictedUpdateEvent(self.h, 0.0, self._step)
        self.DeclareStateOutputPort("motor_state", motor)
        self.DeclareVectorOutputPort("link_actuation", BasicVector(n), self._calc)

    def spring_torque(self, motor: np.ndarray, link: np.ndarray) -> np.ndarray:
        n = self.n
        return self.stiffness * (motor[:n] - link[:n]) + self.damping * (motor[n:] - link[n:])

    def _calc(self, context, output):
        motor, link = context.get_discrete_state_vector().value(), self.link_state.Eval(context)
        output.SetFromVector(self.spring_torque(motor, link) + self.damping * link[self.n :])

    def _step(self, context, state):
        motor = context.get_discrete_state_vector().value()
        tau_s = self.spring_torque(motor, self.link_state.Eval(context))
        w = motor[self.n :] + self.h * (self.drive.Eval(context) - tau_s) / self.inertia
        state.get_mutable_discrete_state(self._motor).SetFromVector(np.concatenate([motor[: self.n] + self.h * w, w]))

    def set_equilibrium(self, context: Context, q: np.ndarray, v: np.ndarray, link_torque: np.ndarray) -> None:
        """Motor state that carries `link_torque` (the link's gravity at rest) with the link at (q, v)."""
        context.SetDiscreteState(np.concatenate([q + link_torque / self.stiffness, v]))


class NoisyVelocity(LeafSystem):
    """Encoders whose velocity reading is v + bound (2 u - 1), u the `unit_noise` input (n draws of
    U(0, 1) per step); positions unchanged."""

    def __init__(self, n, bound):
        super().__init__()
        self.n, self.bound = n, float(bound)
        self.state = self.DeclareVectorInputPort("state", 2 * n)
        self.unit_noise = self.DeclareVectorInputPort("unit_noise", n)
        self.DeclareVectorOutputPort("measured_state", BasicVector(2 * n), self._calc)

    def _calc(self, context, output):
        x = self.state.Eval(context).copy()
        x[self.n :] += self.bound * (2.0 * self.unit_noise.Eval(context) - 1.0)
        output.SetFromVector(x)


class StepDelay(LeafSystem):
    """The input `steps` plant steps late, zero before: a FIFO pushed by a periodic unrestricted
    update. Drake's discrete MultibodyPlant (1.51) steps in the unrestricted phase too, so each
    entry is the value of the context the plant's own step read (the torque it received, what
    the estimator and the referee sample). DiscreteTimeDelay and ZeroOrderHold sample in the
    discrete phase, after the plant has stepped: a state-feedback torque re-evaluated at the
    next state, never applied (tests/test_plant_friction.py test_late_*)."""

    def __init__(self, time_step: float, steps: int, n: int) -> None:
        super().__init__()
        self.n = n
        self.input = self.DeclareVectorInputPort("input", n)
        self._fifo = self.DeclareDiscreteState(steps * n)  # oldest first
        self.DeclareVectorOutputPort("delayed", BasicVector(n), self._calc, {self.xd_ticket()})
        self.DeclarePeriodicUnrestrictedUpdateEvent(time_step, 0.0, self._push)

    def _calc(self, context, output):
        output.SetFromVector(context.get_discrete_state(self._fifo).get_value()[: self.n])

    def _push(self, context, state):
        fifo = context.get_discrete_state(self._fifo).get_value()
        state.get_mutable_discrete_state(self._fifo).SetFromVector(
            np.concatenate([fifo[self.n :], self.input.Eval(context)])
        )


class TorqueSensor(LeafSystem):
    """scale * (tau + w) + offset, w = (2 u - 1)(ratio |tau| + floor), u the `unit_noise` input
    (n draws of U(0, 1) per step, from Drake's RandomSource in the station; the input exists only
    when noisy); with lag_s > 0 the signal is first low-passed, lag_s y' + y = raw, exact for a
    torque held over each step: y_k = a y_(k-1) + (1 - a) raw_(k-1), a = exp(-h / lag_s), raw_(k-1) the
    reading of the step [t_(k-1), t_k) that just ended, starting steady; the output is the filter
    state (reading the current step's torque again would lead the continuous law by one step)."""

    def __init__(self, n, time_step, ratio, floor, scale, offset, noisy, lag_s=0.0):
        super().__init__()
        self.ratio, self.floor = float(ratio), float(floor)
        self.scale, self.offset = np.asarray(scale, float), np.asarray(offset, float)
        self.torque = self.DeclareVectorInputPort("torque", n)
        self.unit_noise = self.DeclareVectorInputPort("unit_noise", n) if noisy else None
        self.DeclareVectorOutputPort("measured_torque", BasicVector(n), self._calc)
        self._keep = np.exp(-time_step / lag_s) if lag_s > 0 else 0.0
        if lag_s > 0:
            # Unrestricted (not discrete) updates: at t_k they run before the noise source redraws,
            # so the filter sees the reading a logger or the estimator sees at t_k.
            self._filtered = self.DeclareDiscreteState(n)
            self.DeclareInitializationUnrestrictedUpdateEvent(self._start)
            self.DeclarePeriodicUnrestrictedUpdateEvent(time_step, 0.0, self._step)

    def _raw(self, context):
        tau = self.torque.Eval(context)
        if self.unit_noise is not None:
            tau = tau + (2.0 * self.unit_noise.Eval(context) - 1.0) * (self.ratio * np.abs(tau) + self.floor)
        return self.scale * tau + self.offset

    def _lagged(self, context):
        previous = context.get_discrete_state(self._filtered).get_value()
        return self._keep * previous + (1.0 - self._keep) * self._raw(context)

    def _start(self, context, state):
        state.get_mutable_discrete_state(self._filtered).SetFromVector(self._raw(context))

    def _step(self, context, state):
        # At t_k the update reads the pre-update context: the reading held over [t_(k-1), t_k).
        state.get_mutable_discrete_state(self._filtered).SetFromVector(self._lagged(context))

    def _calc(self, context, output):
        output.SetFromVector(
            context.get_discrete_state(self._filtered).get_value() if self._keep else self._raw(context)
        )


def _per_joint(values, n, default, field):

    if not values:
        return np.full(n, default, float)
    arr = np.asarray(values, float)
    if arr.shape != (n,):
        raise ScenarioError(f"plant.effects.{field}: needs {n} values, got {arr.size}")
    return arr


def _elasticity(eff, n):
    """(stiffness, damping) per joint from plant.effects, or (None, None) when the joints are rigid."""
    if not eff.joint_stiffness_Nm_rad:
        if eff.joint_damping_Nms_rad:
            raise ScenarioError("plant.effects.joint_damping_Nms_rad: needs joint_stiffness_Nm_rad")
        return None, None
    stiffness = _per_joint(eff.joint_stiffness_Nm_rad, n, 0.0, "joint_stiffness_Nm_rad")
    if np.any(stiffness <= 0):
        raise ScenarioError("plant.effects.joint_stiffness_Nm_rad: values must be > 0")
    if eff.joint_elasticity not in ("quasi_static", "dynamic"):
        raise ScenarioError(f"plant.effects.joint_elasticity: '{eff.joint_elasticity}' is not quasi_static or dynamic")
    damping = _per_joint(eff.joint_damping_Nms_rad, n, 0.0, "joint_damping_Nms_rad")
    if np.any(damping < 0):
        raise ScenarioError("plant.effects.joint_damping_Nms_rad: values must be >= 0")
    if eff.joint_damping_Nms_rad and eff.joint_elasticity != "dynamic":
        raise ScenarioError("plant.effects.joint_damping_Nms_rad: only with joint_elasticity: dynamic")
    return stiffness, damping


# The springs are explicit in the coupled links + motors system (and the damper on the motors'
# side): symplectic Euler is stable on a mode of frequency omega and damping rate c while
# (h omega)^2 + 2 h c < 4; allowed up to half of that, for the stiffest mode without the payload
# over q0 and seeded random configurations in the joint limits (the link inertias change with q).
ELASTIC_STEP_LIMIT = 2.0
ELASTIC_CHECK_CONFIGURATIONS = 64


def _check_elastic_step(plant, joints, payload_body, scenario, stiffness, damping, motor_inertia, h):
    from scipy.linalg import eigh

    ctx = plant.CreateDefaultContext()
    payload_body.SetSpatialInertiaInBodyFrame(ctx, SpatialInertia.Zero())
    idx = [joint.velocity_start() for joint in joints]
    n = len(idx)
    lower = np.array([max(j.position_lower_limits()[0], -np.pi) for j in joints])
    upper = np.array([min(j.position_upper_limits()[0], np.pi) for j in joints])
    poses = np.vstack(
        [scenario.q0_rad, np.random.default_rng(0).uniform(lower, upper, (ELASTIC_CHECK_CONFIGURATIONS, n))]
    )
    mass = np.zeros((2 * n, 2 * n))  # links (q) and motors (theta_m)
    mass[n:, n:] = np.diag(motor_inertia)
    springs = np.kron(np.array([[1.0, -1.0], [-1.0, 1.0]]), np.diag(stiffness))
    omega = 0.0
    for q in poses:
        for joint, angle in zip(joints, q):
            joint.set_angle(ctx, float(angle))
        mass[:n, :n] = plant.CalcMassMatrix(ctx)[np.ix_(idx, idx)]
        omega = max(omega, np.sqrt(max(float(eigh(springs, mass, eigvals_only=True)[-1]), 0.0)))
    rate = float(np.max(damping / motor_inertia))
    measure = (h * omega) ** 2 + 2 * h * rate
    if measure > ELASTIC_STEP_LIMIT:
        raise ScenarioError(
            f"plant.effects.joint_stiffness_Nm_rad: the joint springs (fastest mode {omega:.0f} rad/s without the "
            f"payload) are too stiff for plant.time_step_s {h:g}: (h omega)^2 + 2 h max(D/B) = {measure:.2f} > "
            f"{ELASTIC_STEP_LIMIT} (explicit coupling); lower them or the time step"
        )


def add_real_arm(
    builder: DiagramBuilder,
    scenario: Scenario,
    robot: RobotModel | None = None,
    dumbbell: Dumbbell | str | None = "scenario",
    seed: int | None = None,
    releasable: bool = False,
) -> RealArm:
    """Add the real arm station to `builder` as one sub-Diagram named "real_arm"; returns a
    RealArm with its exported ports: input commanded_torque; outputs state (encoders),
    measured_torque, motor_torque, applied_torque, plant_state, query_object.

    dumbbell: "scenario" (the scenario's payload), a Dumbbell, or None (no payload at start).
    releasable: add the free body RealArm.release hands the payload to (module docstring).
    """

    robot = robot or robot_from_scenario(scenario)
    fill_robot_defaults(scenario, robot, PER_JOINT)  # a Scenario made in code (the arm needs no prior)
    n = robot.n
    h = scenario.plant.time_step_s
    eff = scenario.plant.effects
    db = scenario_dumbbell(scenario) if isinstance(dumbbell, str) and dumbbell == "scenario" else dumbbell
    db = faults.heavier_payload(db, scenario.faults.payload_extra_mass_kg)

    seed = scenario.seed if seed is None else seed
    theta, inertials = real_robot_theta(robot, scenario, seed)
    stiffness, damping = _elasticity(eff, n)
    dynamic_elasticity = stiffness is not None and eff.joint_elasticity == "dynamic"
    fric = theta[10 * n :].reshape(n, 4)  # [Fc, Fv, Ia, beta] per joint
    station = DiagramBuilder()
    plant, scene_graph, instance = _make_real_plant(robot, inertials, h, station)
    plant.set_name("real_arm_plant")
    jp = robot.joint_params
    joints = [plant.GetJointByName(name, instance) for name in jp.names]
    actuators = {
        plant.get_joint_actuator(i).joint().name(): plant.get_joint_actuator(i) for i in plant.GetJointActuatorIndices()
    }
    for k, joint in enumerate(joints):
        if joint.name() not in actuators:
            raise ScenarioError(f"{robot.source}: joint {joint.name()} has no actuator")
        act = actuators[joint.name()]
        if dynamic_elasticity:  # the link's share of the damper, -D v (ElasticTransmission)
            joint.set_default_damping(joint.default_damping() + float(damping[k]))
        act.set_default_gear_ratio(1.0)
        # Reflected inertia Ia on the mass matrix; with dynamic elasticity it is the motor's instead.
        act.set_default_rotor_inertia(0.0 if dynamic_elasticity else float(fric[k, 2]))
    # Payload body welded at the grasp point (its frame: origin at the dumbbell centre, x along it).
    ee_body = plant.GetBodyByName(robot.body_names[robot.end_effector], instance)
    payload_instance = plant.AddModelInstance("payload")
    payload_body = plant.AddRigidBody(
        "payload", payload_instance, _dumbbell_spatial_inertia(db) if db is not None else SpatialInertia.Zero()
    )
    plant.WeldFrames(ee_body.body_frame(), payload_body.body_frame(), RigidTransform(robot.extra["grasp_point"]))
    if db is not None:
        _register_dumbbell_geometry(plant, payload_body, db)
    released_body = None
    if releasable and db is not None:
        released_body = plant.AddRigidBody(
            "released_payload", plant.AddModelInstance("released_payload"), _dumbbell_spatial_inertia(db)
        )
        _register_dumbbell_geometry(plant, released_body, db, prefix="released")
        plant.SetDefaultFloatingBaseBodyPose(released_body, _PARKED)
    _register_obstacles(plant, scenario)
    tilt = _per_joint(eff.base_tilt_rad, 2, 0.0, "base_tilt_rad")
    if np.any(tilt != 0):
        g = plant.gravity_field().gravity_vector()
        rot = RollPitchYaw(tilt[0], tilt[1], 0.0).ToRotationMatrix().matrix()
        plant.mutable_gravity_field().set_gravity_vector(rot.T @ g)
    # Saturation acts on the motor torque (the Saturation system below); Drake's own clamp would
    # act on motor torque minus friction, so it is removed.
    plant.RemoveAllJointActuatorEffortLimits()
    plant.Finalize()
    # The arm's own spheres overlap at the joints: no self-contact (obstacles and floor only).
    robot_bodies = [plant.get_body(i) for i in plant.GetBodyIndices(instance)] + [payload_body]
    robot_geometries = plant.CollectRegisteredGeometries(robot_bodies)
    scene_graph.collision_filter_manager().Apply(CollisionFilterDeclaration().ExcludeWithin(robot_geometries))
    if released_body is not None:  # it leaves the gripper through the fingers, held or falling
        scene_graph.collision_filter_manager().Apply(
            CollisionFilterDeclaration().ExcludeBetween(
                robot_geometries, plant.CollectRegisteredGeometries([released_body])
            )
        )
    inspector = scene_graph.model_inspector()
    payload_collision = tuple(
        (gid, ProximityProperties(inspector.GetProximityProperties(gid)))
        for gid in plant.GetCollisionGeometriesForBody(payload_body)
    )

    sat = station.AddSystem(Saturation(-jp.torque_limit, jp.torque_limit))
    sat.set_name("actuator_saturation")
    delay_steps = int(round(eff.time_delay_s / h))
    applied_port = sat.get_output_port()
    if delay_steps > 0:
        delay = station.AddSystem(StepDelay(h, delay_steps, n))
        delay.set_name("actuation_delay")
        station.Connect(sat.get_output_port(), delay.get_input_port())
        applied_port = delay.get_output_port()
    friction = station.AddSystem(
        JointFriction(
            fric[:, 0],
            fric[:, 1],
            fric[:, 3],
            robot.coulomb_smoothing,
            _per_joint(eff.load_friction_mu, n, 0.0, "load_friction_mu"),
            _per_joint(eff.stribeck_friction_Nm, n, 0.0, "stribeck_friction_Nm"),
            eff.stribeck_velocity_rad_s,
        )
    )
    friction.set_name("joint_friction")
    station.Connect(applied_port, friction.applied)
    state_out = plant.get_state_output_port(instance)
    transmission = None
    if dynamic_elasticity:
        _check_elastic_step(plant, joints, payload_body, scenario, stiffness, damping, fric[:, 2], h)
        transmission = station.AddSystem(ElasticTransmission(stiffness, damping, fric[:, 2], h))
        transmission.set_name("elastic_transmission")
        station.Connect(transmission.GetOutputPort("motor_state"), friction.state)
        station.Connect(friction.get_output_port(), transmission.drive)
        station.Connect(state_out, transmission.link_state)
        station.Connect(transmission.GetOutputPort("link_actuation"), plant.get_actuation_input_port(instance))
    else:
        station.Connect(state_out, friction.state)
        station.Connect(friction.get_output_port(), plant.get_actuation_input_port(instance))
    if stiffness is not None and not dynamic_elasticity:
        encoders = station.AddSystem(SeriesElasticEncoders(stiffness))
        encoders.set_name("motor_side_encoders")
        station.Connect(plant.get_state_output_port(instance), encoders.state)
        station.Connect(friction.get_output_port(), encoders.transmitted)
        state_out = encoders.get_output_port()
    velocity_noise = None
    if eff.velocity_noise_rad_s > 0:
        velocity_noise = station.AddSystem(RandomSource(RandomDistribution.kUniform, n, h))
        velocity_noise.set_name("velocity_noise")
        encoders = station.AddSystem(NoisyVelocity(n, eff.velocity_noise_rad_s))
        encoders.set_name("noisy_velocity_encoders")
        station.Connect(state_out, encoders.state)
        station.Connect(velocity_noise.get_output_port(), encoders.unit_noise)
        state_out = encoders.get_output_port()
    noise = scenario.noise
    noisy = noise.distribution == "uniform"
    sensor = station.AddSystem(
        TorqueSensor(
            n,
            h,
            noise.torque_ratio,
            noise.torque_floor_Nm,
            _per_joint(eff.torque_sensor_scale, n, 1.0, "torque_sensor_scale"),
            _per_joint(eff.torque_sensor_offset_Nm, n, 0.0, "torque_sensor_offset_Nm"),
            noisy,
            eff.torque_sensor_lag_s,
        )
    )
    sensor.set_name("torque_sensor")
    station.Connect(sat.get_output_port(), sensor.torque)
    noise_source = None
    if noisy:  # one U(0, 1) draw per joint and step, seeded through the context (RealArm.seed_noise)
        noise_source = station.AddSystem(RandomSource(RandomDistribution.kUniform, n, h))
        noise_source.set_name("torque_noise")
        station.Connect(noise_source.get_output_port(), sensor.unit_noise)
    measured = sensor.get_output_port()
    sensor_delay_steps = int(round(eff.torque_sensor_delay_s / h))
    if sensor_delay_steps > 0:
        late = station.AddSystem(StepDelay(h, sensor_delay_steps, n))
        late.set_name("torque_sensor_delay")
        station.Connect(measured, late.get_input_port())
        measured = late.get_output_port()
    measured, state_out, injected = faults.add_fault_stages(station, scenario, n, h, measured, state_out)

    station.ExportInput(sat.get_input_port(), "commanded_torque")
    if injected.samples is not None:
        station.ExportOutput(injected.samples, "estimator_samples")
    for port, name in (
        (state_out, "state"),
        (measured, "measured_torque"),
        (sat.get_output_port(), "motor_torque"),
        (applied_port, "applied_torque"),
        (plant.get_state_output_port(instance), "plant_state"),
        (scene_graph.get_query_output_port(), "query_object"),
    ):
        station.ExportOutput(port, name)
    system = builder.AddSystem(station.Build())
    system.set_name("real_arm")
    out = system.GetOutputPort
    return RealArm(
        robot=robot,
        plant=plant,
        scene_graph=scene_graph,
        instance=instance,
        payload_body=payload_body,
        dumbbell=db,
        commanded_torque_input=system.GetInputPort("commanded_torque"),
        state_output=out("state"),
        measured_torque_output=out("measured_torque"),
        applied_torque_output=out("applied_torque"),
        motor_torque_output=out("motor_torque"),
        torque_sensor=sensor,
        time_step=h,
        payload_collision=payload_collision,
        robot_geometries=robot_geometries,
        theta=theta,
        system=system,
        plant_state_output=out("plant_state"),
        query_output=out("query_object"),
        noise_source=noise_source,
        seed=int(seed),
        released_body=released_body,
        transmission=transmission,
        fault_stages=injected.stages,
        fault_sources=(*injected.sources, *([velocity_noise] if velocity_noise else [])),  # seeded streams
        estimator_samples_output=out("estimator_samples") if injected.samples else None,
    )
