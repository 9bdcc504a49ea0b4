"""The robot as the world sees it: a discrete MultibodyPlant with the true payload, friction,
armature, saturation, a noisy torque sensor, encoders and optional unmodelled effects.

Signal path (everything from the scenario and the RobotModel; nothing hard-coded):

    commanded torque u -> Saturation(+-torque_limit)  = motor torque tau_m   -> TorqueSensor
                       -> [DiscreteTimeDelay d]        = applied torque tau_a
                       -> JointFriction: tau_a - (Fc tanh(v/vs) + Fv v + beta)  -> plant actuation
    plant state (q, v) -> [SeriesElasticEncoders]      -> state output

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

Robot parameters (scenario.plant.robot_parameters): "nominal" uses the model's theta exactly;
"drawn" draws every link's inertial parameters and every joint's friction, armature and offset
uniformly inside the declared box nominal +- max(theta_r_ratio |nominal|, floor) (the box the
controller, planner and estimator assume; seeded by the run's seed); "corner" takes a random
vertex of it. A link whose drawn parameters are not physically consistent (pseudo-inertia not
positive definite) has its deviation halved until it is, so it stays inside the box; the links
are built from a copy of the URDF with those inertials. RealArm.theta is what the plant uses.

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
"""

from __future__ import annotations

import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydrake.common import RandomDistribution, RandomGenerator
from pydrake.geometry import Box, CollisionFilterDeclaration, Cylinder, ProximityProperties, Role
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.plant import CoulombFriction
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.framework import BasicVector, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import DiscreteTimeDelay, RandomSource, Saturation, ZeroOrderHold

from . import faults, inertial
from .config import ScenarioError, resolve_path, robot_from_scenario, scenario_dir
from .payload import Dumbbell, load_dumbbells, payload_theta_in_end_effector
from .robot_model import make_plant
from .uncertainty import parameter_radius


def scenario_dumbbell(scenario):
    """The Dumbbell the scenario names, or None for payload.dumbbell == 'none'."""

    name = scenario.payload.dumbbell
    if name.lower() == "none":
        return None
    bells = load_dumbbells(resolve_path(scenario.payload.dumbbells_file, scenario_dir(scenario)))
    if name not in bells:
        raise ScenarioError(f"{scenario.source}: payload.dumbbell: {name!r} is not one of {', '.join(bells)}")
    return bells[name]


def true_theta(robot, dumbbell, theta=None):
    """The plant's true 14 n parameters: the robot's (the model's nominal by default) plus the
    payload on the end effector."""
    theta = (robot.theta if theta is None else np.asarray(theta, float)).copy()
    theta[robot.ee_slice] += payload_theta_in_end_effector(dumbbell, robot.extra["grasp_point"])
    return theta


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


_PD_MARGIN = 1e-3  # a drawn link keeps λ_min(pseudo-inertia) ≥ this share of its nominal one


def draw_robot_theta(robot, radius, rng, mode="drawn", link_theta=None):
    """The real arm's 14 n parameters inside robot.theta ± radius: uniform ("drawn") or a random
    vertex ("corner"). link_theta (n, 10): each moving link's OWN inertial parameters (the body a
    deviation is applied to; default: robot.theta's bodies); a link deviation that would make its
    pseudo-inertia lose positive definiteness is halved until it does not."""

    n = robot.n
    theta0 = robot.theta
    unit = rng.choice([-1.0, 1.0], theta0.shape) if mode == "corner" else rng.uniform(-1.0, 1.0, theta0.shape)
    delta = unit * radius
    own = theta0[: 10 * n].reshape(n, 10) if link_theta is None else np.asarray(link_theta, float)
    for i in range(n):
        d = delta[10 * i : 10 * i + 10]
        floor = _PD_MARGIN * np.linalg.eigvalsh(inertial.pseudo_inertia(own[i])).min()
        while not inertial.is_physically_consistent(own[i] + d, floor):
            d *= 0.5
    return theta0 + delta


def _robot_parameter_box(robot, scenario):

    ratio = scenario.noise.theta_r_ratio
    return parameter_radius(robot, ratio, ratio, scenario.noise.theta_r_floor)


def _link_inertials(plant, names):

    return np.array(
        [inertial.from_spatial_inertia(plant.GetBodyByName(name).default_spatial_inertia()) for name in names]
    )


def _urdf_with_inertials(source, inertials, directory):
    """A copy of the URDF at `source` whose named links carry the given inertials ({link: theta
    about the link origin}); relative mesh paths made absolute. Returns its path."""

    source = Path(source)
    tree = ET.parse(source)
    root = tree.getroot()
    for mesh in root.iter("mesh"):
        name = mesh.get("filename", "")
        if name and "://" not in name and not Path(name).is_absolute():
            mesh.set("filename", str((source.parent / name).resolve()))
    links = {link.get("name"): link for link in root.iter("link")}
    for name, th in inertials.items():
        m, com = th[0], th[1:4] / th[0]
        i_com = inertial.inertia_matrix(th) - m * (com @ com * np.eye(3) - np.outer(com, com))
        old = links[name].find("inertial")
        if old is not None:
            links[name].remove(old)
        node = ET.SubElement(links[name], "inertial")
        ET.SubElement(node, "origin", xyz=" ".join(repr(float(c)) for c in com), rpy="0 0 0")
        ET.SubElement(node, "mass", value=repr(float(m)))
        ET.SubElement(
            node,
            "inertia",
            **{
                k: repr(float(i_com[a, b]))
                for k, (a, b) in {
                    "ixx": (0, 0),
                    "iyy": (1, 1),
                    "izz": (2, 2),
                    "ixy": (0, 1),
                    "ixz": (0, 2),
                    "iyz": (1, 2),
                }.items()
            },
        )
    path = Path(directory) / source.name
    tree.write(path)
    return path


def real_robot_theta(robot, scenario, seed):
    """(theta, link inertials) of the real arm: the nominal model (inertials None), or parameters
    drawn in the box (plant.robot_parameters) with {link name: its own drawn inertial theta}."""

    mode = scenario.plant.robot_parameters
    if mode == "nominal":
        return robot.theta.copy(), None
    if Path(robot.source).suffix.lower() != ".urdf":
        raise ScenarioError(
            f"{scenario.source}: plant.robot_parameters: {mode!r} needs a URDF model, got {robot.source}"
        )
    nominal_plant, _, _ = make_plant(robot.source)
    own = _link_inertials(nominal_plant, robot.body_names)
    rng = np.random.default_rng([int(seed), 0x5EED])  # its own stream: not the sensor noise's
    theta = draw_robot_theta(robot, _robot_parameter_box(robot, scenario), rng, mode, own)
    return theta, {
        name: own[i] + theta[10 * i : 10 * i + 10] - robot.theta[10 * i : 10 * i + 10]
        for i, name in enumerate(robot.body_names)
    }


def _make_real_plant(robot, inertials, time_step, builder):
    """make_plant of the model, or of a temporary copy of its URDF with the drawn inertials."""

    if inertials is None:
        return make_plant(robot.source, time_step, builder=builder)
    with tempfile.TemporaryDirectory(prefix="safesysid_real_arm_") as directory:
        return make_plant(_urdf_with_inertials(robot.source, inertials, directory), time_step, builder=builder)


@dataclass
class RealArm:
    """The real arm station: `system` is the sub-Diagram "real_arm" added to the caller's builder
    (as manipulation's MakeHardwareStation), the ports are its exported ones, and plant,
    scene_graph, instance, payload_body are handles into it (their contexts: from the root's)."""

    robot: object  # RobotModel
    plant: object
    scene_graph: object
    instance: object
    payload_body: object
    dumbbell: Dumbbell | None
    commanded_torque_input: object  # InputPort (n)
    state_output: object  # OutputPort (2n): encoders q, v
    measured_torque_output: object  # OutputPort (n)
    applied_torque_output: object  # OutputPort (n): torque reaching the joints (saturated, delayed)
    motor_torque_output: object  # OutputPort (n): saturated command (what the sensor measures)
    torque_sensor: object
    time_step: float
    payload_collision: tuple = ()  # ((GeometryId, ProximityProperties), ...) of the dumbbell
    robot_geometries: object = None  # GeometrySet of the arm + payload (no self-contact)
    theta: np.ndarray = None  # the robot's 14 n parameters the plant uses (no payload)
    system: object = None  # the Diagram "real_arm"
    plant_state_output: object = None  # OutputPort (2n): the plant's true q, v (not the encoders')
    query_output: object = None  # OutputPort: SceneGraph's QueryObject (true geometry)
    noise_source: object = None  # RandomSource of the torque sensor's noise (None: noiseless)
    seed: int = 0  # the run's seed: drawn parameters at build, sensor noise via seed_noise
    released_body: object = None  # free body taking the payload over at release (None: not releasable)
    # Injected faults (scenario `faults`, systems/faults.py): the stages (their events), their
    # RandomSources (seeded with the noise), and the estimator's packet port when samples are faulty.
    fault_stages: tuple = ()
    fault_sources: tuple = ()
    estimator_samples_output: object = None  # OutputPort faults.packet_size(n) or None

    @property
    def n(self):
        return self.robot.n

    def plant_context(self, root_context):
        return self.plant.GetMyMutableContextFromRoot(root_context)

    def set_payload(self, root_context, dumbbell: Dumbbell | None):
        """Grasp (a Dumbbell) or release (None) at run time."""

        ctx = self.plant_context(root_context)
        spatial = _dumbbell_spatial_inertia(dumbbell) if dumbbell is not None else SpatialInertia.Zero()
        self.payload_body.SetSpatialInertiaInBodyFrame(ctx, spatial)
        self._set_payload_collision(root_context, dumbbell is not None)

    def _set_payload_collision(self, root_context, present):
        """A released dumbbell stops colliding (its proximity role leaves the context's model)."""

        if not self.payload_collision:
            return
        sg_ctx = self.scene_graph.GetMyMutableContextFromRoot(root_context)
        inspector = self.scene_graph.get_query_output_port().Eval(sg_ctx).inspector()
        source = self.plant.get_source_id()
        changed = False
        for gid, props in self.payload_collision:
            has = inspector.GetProximityProperties(gid) is not None
            if present and not has:
                self.scene_graph.AssignRole(sg_ctx, source, gid, props)
                changed = True
            elif not present and has:
                self.scene_graph.RemoveRole(sg_ctx, source, gid, Role.kProximity)
        if changed:  # a re-assigned role starts unfiltered: no contact with the arm, again
            self.scene_graph.collision_filter_manager(sg_ctx).Apply(
                CollisionFilterDeclaration().ExcludeWithin(self.robot_geometries)
            )

    def payload_pose(self, root_context):
        """RigidTransform of the payload in the world: the released body once released, else the
        welded one (its frame: the dumbbell centre, x along the handle)."""

        ctx = self.plant_context(root_context)
        released = self.released_body is not None and not self.released_body.is_locked(ctx)
        return (self.released_body if released else self.payload_body).EvalPoseInWorld(ctx)

    def payload_speed(self, root_context):
        """|v| of the payload centre in the world [m/s]."""

        ctx = self.plant_context(root_context)
        released = self.released_body is not None and not self.released_body.is_locked(ctx)
        body = self.released_body if released else self.payload_body
        return float(np.linalg.norm(body.EvalSpatialVelocityInWorld(ctx).translational()))

    def release(self, root_context):
        """Let go of the payload: the free body takes the welded payload's pose and spatial
        velocity (momentum kept) and is unlocked; the welded one is emptied. Returns the pose."""

        if self.released_body is None or self.dumbbell is None:
            raise RuntimeError("release: the station was built without a releasable payload")
        ctx = self.plant_context(root_context)
        pose = self.payload_body.EvalPoseInWorld(ctx)
        velocity = self.payload_body.EvalSpatialVelocityInWorld(ctx)
        self.set_payload(root_context, None)
        self.released_body.Unlock(ctx)
        self.plant.SetFreeBodyPose(ctx, self.released_body, pose)
        self.plant.SetFreeBodySpatialVelocity(ctx, self.released_body, velocity)
        return pose

    def seed_noise(self, root_context, seed=None):
        """Seed the sensor noise of this context (the station's seed unless given): Drake's
        SetRandomContext(RandomGenerator(seed)) on the noise source only, so the rest of the
        context is kept. Unseeded, a RandomSource draws from a default seed of its own."""
        seed = int(self.seed if seed is None else seed)
        for k, source in enumerate((self.noise_source, *self.fault_sources)):
            if source is not None:  # a stream per source (k = 0: the sensor noise, as before)
                source.SetRandomContext(
                    source.GetMyMutableContextFromRoot(root_context), RandomGenerator(seed + 7919 * k)
                )

    def fault_events(self, root_context):
        """[{t, kind, detail}] of the injected faults (scenario `faults`)."""
        return [e for stage in self.fault_stages for e in stage.events(stage.GetMyContextFromRoot(root_context))]

    def set_state(self, root_context, q, v=None):
        ctx = self.plant_context(root_context)
        self.plant.SetPositions(ctx, self.instance, np.asarray(q, float))
        self.plant.SetVelocities(ctx, self.instance, np.zeros(self.n) if v is None else np.asarray(v, float))
        if self.released_body is not None:  # waiting, locked, for a release
            self.plant.SetFreeBodyPose(ctx, self.released_body, _PARKED)
            self.released_body.Lock(ctx)

    def true_theta(self, dumbbell="current"):
        return true_theta(self.robot, self.dumbbell if dumbbell == "current" else dumbbell, self.theta)


def _dumbbell_spatial_inertia(db: Dumbbell):

    return inertial.to_spatial_inertia(db.theta_about_centre())


_PARKED = RigidTransform([0.0, 0.0, -3.0])  # the released body's pose until the release: far below the floor


def _register_dumbbell_geometry(plant, body, db: Dumbbell, prefix="dumbbell"):

    along_x = RotationMatrix.MakeYRotation(np.pi / 2)  # Drake cylinders run along z
    friction = CoulombFriction(0.8, 0.6)
    for k, (_, x, radius, length) in enumerate(db.parts()):
        pose = RigidTransform(along_x, [x, 0.0, 0.0])
        name = f"{prefix}_{db.name}_{['handle', 'head_pos', 'head_neg'][k]}"
        plant.RegisterVisualGeometry(body, pose, Cylinder(radius, length), name + "_visual", [0.15, 0.15, 0.18, 1.0])
        plant.RegisterCollisionGeometry(body, pose, Cylinder(radius, length), name, friction)


def _register_obstacles(plant, scenario):

    world = plant.world_body()
    friction = CoulombFriction(0.8, 0.6)
    # Obstacles that appear later (faults) are in the referee's world from the start (stricter).
    for k, ob in enumerate(list(scenario.obstacles) + list(scenario.faults.appearing_obstacles)):
        pose = RigidTransform(RollPitchYaw(np.asarray(ob.rpy_rad, float)), np.asarray(ob.xyz_m, float))
        box = Box(*np.asarray(ob.size_m, float))
        name = f"obstacle_{k}_{ob.name}"
        plant.RegisterVisualGeometry(world, pose, box, name + "_visual", [0.8, 0.3, 0.2, 0.6])
        plant.RegisterCollisionGeometry(world, pose, box, name, friction)
    # Floor: a thick slab whose top face is the floor plane.
    thickness = 0.05
    pose = RigidTransform([0.0, 0.0, scenario.planner.floor_z_m - thickness / 2])
    plant.RegisterVisualGeometry(world, pose, Box(4.0, 4.0, thickness), "floor_visual", [0.6, 0.6, 0.6, 0.3])
    plant.RegisterCollisionGeometry(world, pose, Box(4.0, 4.0, thickness), "floor", friction)


@dataclass
class _Injected:
    stages: tuple = ()
    sources: tuple = ()
    samples: object = None  # the estimator's packet port (SampleFaults), or None


def _add_fault_stages(station, scenario, n, h, measured, state_out):
    """The scenario's fault stages (systems/faults.py) on the measured torque and the encoders,
    and the faulty link to the estimator: (measured torque, state, _Injected)."""

    f, injected = scenario.faults, _Injected()

    def add(system, name, draws=0):
        system.set_name(name)
        injected.stages += (station.AddSystem(system),)
        if draws:
            source = station.AddSystem(RandomSource(RandomDistribution.kUniform, draws, h))
            source.set_name(f"{name}_draws")
            station.Connect(source.get_output_port(), system.unit_noise)
            injected.sources += (source,)
        return system

    if f.torque_spike_magnitude_Nm * f.torque_spike_rate_per_s > 0 or f.torque_dropout_duration_s > 0:
        joints = [j - 1 for j in f.torque_spike_joints]
        spikes = f.torque_spike_magnitude_Nm * f.torque_spike_rate_per_s > 0
        stage = faults.TorqueSensorFaults(
            n,
            h,
            f.torque_spike_magnitude_Nm,
            f.torque_spike_rate_per_s,
            joints,
            f.torque_dropout_start_s,
            f.torque_dropout_duration_s,
        )
        add(stage, "fault_torque_sensor", 2 if spikes else 0)
        station.Connect(measured, stage.torque)
        measured = stage.get_output_port()
    if f.velocity_clip_rad_s > 0:
        stage = add(faults.VelocityClip(n, h, f.velocity_clip_rad_s), "fault_velocity_clip")
        station.Connect(state_out, stage.state)
        state_out = stage.get_output_port()
    if f.samples_faulty():
        stage = add(faults.SampleFaults(n, h, faults.SampleRates.from_faults(f, h)), "fault_samples", 5)
        station.Connect(state_out, stage.state)
        station.Connect(measured, stage.torque)
        injected.samples = stage.get_output_port()
    return measured, state_out, injected


def add_real_arm(builder, scenario, robot=None, dumbbell="scenario", seed=None, releasable=False):
    """Add the real arm station to `builder` as one sub-Diagram named "real_arm"; returns a
    RealArm with its exported ports: input commanded_torque; outputs state (encoders),
    measured_torque, motor_torque, applied_torque, plant_state, query_object.

    dumbbell: "scenario" (the scenario's payload), a Dumbbell, or None (no payload at start).
    releasable: add the free body RealArm.release hands the payload to (module docstring).
    """

    robot = robot or robot_from_scenario(scenario)
    n = robot.n
    h = scenario.plant.time_step_s
    eff = scenario.plant.effects
    db = scenario_dumbbell(scenario) if isinstance(dumbbell, str) and dumbbell == "scenario" else dumbbell
    db = faults.heavier_payload(db, scenario.faults.payload_extra_mass_kg)

    seed = scenario.seed if seed is None else seed
    theta, inertials = real_robot_theta(robot, scenario, seed)
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
        act.set_default_gear_ratio(1.0)
        act.set_default_rotor_inertia(float(fric[k, 2]))  # reflected inertia = Ia
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
        delay = station.AddSystem(DiscreteTimeDelay(h, delay_steps, n))
        delay.set_name("actuation_delay")
        station.Connect(sat.get_output_port(), delay.get_input_port())
        applied_port = delay.get_output_port()
    stiffness = (
        _per_joint(eff.joint_stiffness_Nm_rad, n, 0.0, "joint_stiffness_Nm_rad") if eff.joint_stiffness_Nm_rad else None
    )
    if stiffness is not None and np.any(stiffness <= 0):
        raise ScenarioError("plant.effects.joint_stiffness_Nm_rad: values must be > 0")
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
    station.Connect(plant.get_state_output_port(instance), friction.state)
    station.Connect(friction.get_output_port(), plant.get_actuation_input_port(instance))
    state_out = plant.get_state_output_port(instance)
    if stiffness is not None:
        encoders = station.AddSystem(SeriesElasticEncoders(stiffness))
        encoders.set_name("motor_side_encoders")
        station.Connect(plant.get_state_output_port(instance), encoders.state)
        station.Connect(friction.get_output_port(), encoders.transmitted)
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
        # A sampled element already holds the torque one step (the command is published before the
        # step's update samples it), so N - 1 buffered steps make a reading N steps late
        # (tests/test_corrected_model.py: 0.03 s is diagnosed as 0.030 s). The noise draw, a
        # discrete state of its own, lags one step less; white noise, so no test can tell.
        late = station.AddSystem(
            DiscreteTimeDelay(h, sensor_delay_steps - 1, n) if sensor_delay_steps > 1 else ZeroOrderHold(h, n)
        )
        late.set_name("torque_sensor_delay")
        station.Connect(measured, late.get_input_port())
        measured = late.get_output_port()
    measured, state_out, injected = _add_fault_stages(station, scenario, n, h, measured, state_out)

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
        fault_stages=injected.stages,
        fault_sources=injected.sources,
        estimator_samples_output=out("estimator_samples") if injected.samples else None,
    )
