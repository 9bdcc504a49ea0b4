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
box) and the plant's scene: systems/plant/arm_plant.py; the LeafSystems of the signal path:
systems/plant/stages.py; the fault stages: systems/plant/faults.py.

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
  transmission carried over the last plant step (applied torque minus friction; one step behind,
  which keeps the controller's feedback free of an algebraic loop). Velocities are reported unchanged. This
  captures the torque-proportional position offset of a stiff gearbox, not its resonance. It needs
  K above the controller's position gain: the offset feeds back one step late with gain
  (position gain) / K per step, and beyond 1 the command flips sign every step and grows to the
  torque limit (docs/diagnosis-closed-loop.md); softer joints need joint_elasticity: dynamic.
  With joint_elasticity: dynamic (and joint_damping_Nms_rad) it is the flexible-joint model
  instead (ElasticTransmission): the armature becomes a motor of its own, driven by the applied
  torque against its friction, and a spring-damper carries the torque to the link; encoders and
  the referee read the link, the torque sensor still the motor torque. The springs are explicit:
  stiff ones need a small plant.time_step_s (checked at build, _check_elastic_step).
- velocity_noise_rad_s: the encoders' velocities carry uniform noise in +-bound per joint and
  step (a Drake RandomSource seeded with the others), seen by controller and estimator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.common import RandomDistribution
from pydrake.geometry import CollisionFilterDeclaration, ProximityProperties
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.framework import DiagramBuilder, OutputPort
from pydrake.systems.primitives import RandomSource, Saturation
from safesysid.systems.config import Scenario, ScenarioError
from safesysid.systems.model.loading import robot_from_scenario
from safesysid.systems.model.payload import Dumbbell
from safesysid.systems.model.robot_defaults import PER_JOINT, fill_robot_defaults
from safesysid.systems.model.robot_model import RobotModel
from safesysid.systems.plant import faults
from safesysid.systems.plant.arm_plant import (
    PARKED,
    RealArm,
    dumbbell_spatial_inertia,
    make_real_plant,
    real_robot_theta,
    register_dumbbell_geometry,
    register_obstacles,
    scenario_dumbbell,
)
from safesysid.systems.plant.stages import (
    ElasticTransmission,
    JointFriction,
    NoisyVelocity,
    SeriesElasticEncoders,
    StepDelay,
    TorqueSensor,
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
    *,
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
    n, h, eff = robot.n, scenario.plant.time_step_s, scenario.plant.effects
    db = scenario_dumbbell(scenario) if isinstance(dumbbell, str) and dumbbell == "scenario" else dumbbell
    db = faults.heavier_payload(db, scenario.faults.payload_extra_mass_kg)
    seed = scenario.seed if seed is None else seed
    theta, inertials = real_robot_theta(robot, scenario, seed)
    stiffness, damping = _elasticity(eff, n)
    dynamic_elasticity = stiffness is not None and eff.joint_elasticity == "dynamic"
    fric = theta[10 * n :].reshape(n, 4)  # [Fc, Fv, Ia, beta] per joint
    station = DiagramBuilder()
    plant, scene_graph, instance = make_real_plant(robot, inertials, h, builder=station)
    plant.set_name("real_arm_plant")
    joints = _apply_actuators(plant, instance, robot, fric=fric, damping=damping if dynamic_elasticity else None)
    payload_body, released_body = _apply_payload(plant, instance, robot, db, releasable=releasable)
    register_obstacles(plant, scenario)
    _apply_base_tilt(plant, eff)
    plant.RemoveAllJointActuatorEffortLimits()  # Drake's clamp would act on motor torque minus friction
    plant.Finalize()
    robot_geometries, payload_collision = _apply_collision_filters(
        plant, scene_graph, instance, bodies=(payload_body, released_body)
    )
    chain = _apply_actuation(station, plant, instance, robot, eff=eff, fric=fric, time_step=h)
    if dynamic_elasticity:
        _check_elastic_step(plant, joints, payload_body, scenario, stiffness, damping, fric[:, 2], h)
    elastic = (stiffness, damping, fric[:, 2], h) if dynamic_elasticity else None
    transmission = _apply_drive(station, plant, instance, chain, elastic=elastic)
    quasi_static = None if dynamic_elasticity else stiffness
    state_out, velocity_noise = _apply_encoders(station, plant, instance, chain, stiffness=quasi_static, eff=eff, n=n)
    sensor, noise_source, measured = _apply_torque_sensor(station, scenario, chain.saturation, n=n, time_step=h)
    stages = faults.add_fault_stages(station, scenario, n, h=h, measured=measured, state_out=state_out)
    measured, state_out, injected = stages
    system = _export(
        builder, station, plant, instance, scene_graph, chain, injected, state=state_out, measured=measured
    )
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


def _apply_actuators(plant, instance, robot, *, fric, damping):
    """Gear ratio 1 and the reflected inertia Ia on each joint's actuator; with dynamic elasticity
    (damping given) the link's share of the damper, -D v (ElasticTransmission), and the inertia is
    the motor's instead. The joints, in the model's order."""
    joints = [plant.GetJointByName(name, instance) for name in robot.joint_params.names]
    actuators = {
        plant.get_joint_actuator(i).joint().name(): plant.get_joint_actuator(i) for i in plant.GetJointActuatorIndices()
    }
    for k, joint in enumerate(joints):
        if joint.name() not in actuators:
            raise ScenarioError(f"{robot.source}: joint {joint.name()} has no actuator")
        act = actuators[joint.name()]
        if damping is not None:
            joint.set_default_damping(joint.default_damping() + float(damping[k]))
        act.set_default_gear_ratio(1.0)
        act.set_default_rotor_inertia(0.0 if damping is not None else float(fric[k, 2]))
    return joints


def _apply_payload(plant, instance, robot, db, *, releasable):
    """The payload body welded at the grasp point (its frame: origin at the dumbbell centre, x along
    it) and, when releasable, the free body parked below the floor: (payload body, released body or None)."""
    ee_body = plant.GetBodyByName(robot.body_names[robot.end_effector], instance)
    payload_instance = plant.AddModelInstance("payload")
    payload_body = plant.AddRigidBody(
        "payload", payload_instance, dumbbell_spatial_inertia(db) if db is not None else SpatialInertia.Zero()
    )
    plant.WeldFrames(ee_body.body_frame(), payload_body.body_frame(), RigidTransform(robot.extra["grasp_point"]))
    if db is not None:
        register_dumbbell_geometry(plant, payload_body, db)
    released_body = None
    if releasable and db is not None:
        released_body = plant.AddRigidBody(
            "released_payload", plant.AddModelInstance("released_payload"), dumbbell_spatial_inertia(db)
        )
        register_dumbbell_geometry(plant, released_body, db, prefix="released")
        plant.SetDefaultFloatingBaseBodyPose(released_body, PARKED)
    return payload_body, released_body


def _apply_base_tilt(plant, eff):
    """plant.effects.base_tilt_rad: gravity in the base frame is R(roll, pitch)^T g."""
    tilt = _per_joint(eff.base_tilt_rad, 2, 0.0, "base_tilt_rad")
    if np.any(tilt != 0):
        g = plant.gravity_field().gravity_vector()
        rot = RollPitchYaw(tilt[0], tilt[1], 0.0).ToRotationMatrix().matrix()
        plant.mutable_gravity_field().set_gravity_vector(rot.T @ g)


def _apply_collision_filters(plant, scene_graph, instance, *, bodies):
    """No self-contact (the arm's own spheres overlap at the joints: obstacles and floor only); the
    released payload leaves the gripper through the fingers. (robot geometries, the payload's
    collision geometries with their proximity properties)."""
    payload_body, released_body = bodies
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
    return robot_geometries, payload_collision


@dataclass
class _Actuation:
    saturation: Saturation
    applied: OutputPort  # the applied torque (after the optional delay)
    friction: JointFriction


def _apply_actuation(station, plant, instance, robot, *, eff, fric, time_step):
    """Saturation (the motor torque) -> [StepDelay] (the applied torque) -> JointFriction."""
    n, jp = robot.n, robot.joint_params
    sat = station.AddSystem(Saturation(-jp.torque_limit, jp.torque_limit))
    sat.set_name("actuator_saturation")
    delay_steps = int(round(eff.time_delay_s / time_step))
    applied_port = sat.get_output_port()
    if delay_steps > 0:
        delay = station.AddSystem(StepDelay(time_step, delay_steps, n))
        delay.set_name("actuation_delay")
        station.Connect(sat.get_output_port(), delay.get_input_port())
        applied_port = delay.get_output_port()
    friction = station.AddSystem(
        JointFriction(
            fric[:, 0],
            fric[:, 1],
            fric[:, 3],
            robot.coulomb_smoothing,
            load_mu=_per_joint(eff.load_friction_mu, n, 0.0, "load_friction_mu"),
            stribeck=_per_joint(eff.stribeck_friction_Nm, n, 0.0, "stribeck_friction_Nm"),
            stribeck_vs=eff.stribeck_velocity_rad_s,
        )
    )
    friction.set_name("joint_friction")
    station.Connect(applied_port, friction.applied)
    return _Actuation(sat, applied_port, friction)


def _apply_drive(station, plant, instance, chain, *, elastic):
    """JointFriction drives the plant at the link's velocity; with dynamic elasticity (elastic:
    stiffness, damping, motor inertia, time step) at the motor's, and the spring-damper drives the
    link: the ElasticTransmission, or None."""
    if elastic is None:
        station.Connect(plant.get_state_output_port(instance), chain.friction.state)
        station.Connect(chain.friction.get_output_port(), plant.get_actuation_input_port(instance))
        return None
    transmission = station.AddSystem(ElasticTransmission(*elastic))
    transmission.set_name("elastic_transmission")
    station.Connect(transmission.GetOutputPort("motor_state"), chain.friction.state)
    station.Connect(chain.friction.get_output_port(), transmission.drive)
    station.Connect(plant.get_state_output_port(instance), transmission.link_state)
    station.Connect(transmission.GetOutputPort("link_actuation"), plant.get_actuation_input_port(instance))
    return transmission


def _apply_encoders(station, plant, instance, chain, *, stiffness, eff, n):
    """The encoders' state output: motor-side under quasi-static elasticity (stiffness given),
    velocities noisy under plant.effects.velocity_noise_rad_s. (state port, its RandomSource or None)."""
    state_out = plant.get_state_output_port(instance)
    if stiffness is not None:
        encoders = station.AddSystem(SeriesElasticEncoders(stiffness, plant.time_step()))
        encoders.set_name("motor_side_encoders")
        station.Connect(plant.get_state_output_port(instance), encoders.state)
        station.Connect(chain.friction.get_output_port(), encoders.transmitted)
        state_out = encoders.get_output_port()
    velocity_noise = None
    if eff.velocity_noise_rad_s > 0:
        velocity_noise = station.AddSystem(RandomSource(RandomDistribution.kUniform, n, plant.time_step()))
        velocity_noise.set_name("velocity_noise")
        encoders = station.AddSystem(NoisyVelocity(n, eff.velocity_noise_rad_s))
        encoders.set_name("noisy_velocity_encoders")
        station.Connect(state_out, encoders.state)
        station.Connect(velocity_noise.get_output_port(), encoders.unit_noise)
        state_out = encoders.get_output_port()
    return state_out, velocity_noise


def _apply_torque_sensor(station, scenario, sat, *, n, time_step):
    """The torque sensor on the motor torque, its seeded noise source, and the optional reading
    delay: (sensor, noise source or None, measured torque port)."""
    eff, noise = scenario.plant.effects, scenario.noise
    noisy = noise.distribution == "uniform"
    sensor = station.AddSystem(
        TorqueSensor(
            n,
            time_step,
            noise.torque_ratio,
            noise.torque_floor_Nm,
            _per_joint(eff.torque_sensor_scale, n, 1.0, "torque_sensor_scale"),
            _per_joint(eff.torque_sensor_offset_Nm, n, 0.0, "torque_sensor_offset_Nm"),
            noisy,
            lag_s=eff.torque_sensor_lag_s,
        )
    )
    sensor.set_name("torque_sensor")
    station.Connect(sat.get_output_port(), sensor.torque)
    noise_source = None
    if noisy:  # one U(0, 1) draw per joint and step, seeded through the context (RealArm.seed_noise)
        noise_source = station.AddSystem(RandomSource(RandomDistribution.kUniform, n, time_step))
        noise_source.set_name("torque_noise")
        station.Connect(noise_source.get_output_port(), sensor.unit_noise)
    measured = sensor.get_output_port()
    sensor_delay_steps = int(round(eff.torque_sensor_delay_s / time_step))
    if sensor_delay_steps > 0:
        late = station.AddSystem(StepDelay(time_step, sensor_delay_steps, n))
        late.set_name("torque_sensor_delay")
        station.Connect(measured, late.get_input_port())
        measured = late.get_output_port()
    return sensor, noise_source, measured


def _export(builder, station, plant, instance, scene_graph, chain, injected, *, state, measured):
    """Export the station's ports and add it to `builder` as the sub-Diagram "real_arm"."""
    station.ExportInput(chain.saturation.get_input_port(), "commanded_torque")
    if injected.samples is not None:
        station.ExportOutput(injected.samples, "estimator_samples")
    for port, name in (
        (state, "state"),
        (measured, "measured_torque"),
        (chain.saturation.get_output_port(), "motor_torque"),
        (chain.applied, "applied_torque"),
        (plant.get_state_output_port(instance), "plant_state"),
        (scene_graph.get_query_output_port(), "query_object"),
    ):
        station.ExportOutput(port, name)
    system = builder.AddSystem(station.Build())
    system.set_name("real_arm")
    return system
