"""The real arm's plant and scene (systems/plant/station.py wires them into the station): the
scenario's payload, the true parameters, a copy of the URDF with drawn inertials, the payload's and
the obstacles' geometry, and RealArm, the handles into a built station with its run-time
operations (grasp and release, state, noise seeds, fault events).

Robot parameters (scenario.plant.robot_parameters): "nominal" uses the model's theta exactly;
"drawn" draws every link's inertial parameters and every joint's friction, armature and offset
uniformly inside the declared box nominal +- max(theta_r_ratio |nominal|, floor) (the box the
controller, planner and estimator assume; seeded by the run's seed); "corner" takes a random
vertex of it. A link whose drawn parameters are not physically consistent (pseudo-inertia not
positive definite) has its deviation halved until it is, so it stays inside the box; the links
are built from a copy of the URDF with those inertials. RealArm.theta is what the plant uses.
"""

from __future__ import annotations

import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from pydrake.common import RandomGenerator
from pydrake.geometry import (
    Box,
    CollisionFilterDeclaration,
    Cylinder,
    GeometryId,
    GeometrySet,
    ProximityProperties,
    Role,
    SceneGraph,
)
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.plant import CoulombFriction, MultibodyPlant
from pydrake.multibody.tree import ModelInstanceIndex, RigidBody, SpatialInertia
from pydrake.systems.framework import Context, Diagram, DiagramBuilder, InputPort, LeafSystem, OutputPort
from pydrake.systems.primitives import RandomSource
from safesysid.systems.config import Scenario, ScenarioError
from safesysid.systems.model import inertial
from safesysid.systems.model.loading import resolve_path, scenario_dir
from safesysid.systems.model.payload import Dumbbell, load_dumbbells, payload_theta_in_end_effector
from safesysid.systems.model.robot_model import RobotModel, make_plant
from safesysid.systems.model.uncertainty import parameter_radius

if TYPE_CHECKING:
    from safesysid.systems.plant.stages import TorqueSensor


def scenario_dumbbell(scenario: Scenario) -> Dumbbell | None:
    """The Dumbbell the scenario names, or None for payload.dumbbell == 'none'."""

    name = scenario.payload.dumbbell
    if name.lower() == "none":
        return None
    bells = load_dumbbells(resolve_path(scenario.payload.dumbbells_file, scenario_dir(scenario)))
    if name not in bells:
        raise ScenarioError(f"{scenario.source}: payload.dumbbell: {name!r} is not one of {', '.join(bells)}")
    return bells[name]


def true_theta(robot: RobotModel, dumbbell: Dumbbell | None, theta: ArrayLike | None = None) -> np.ndarray:
    """The plant's true 14 n parameters: the robot's (the model's nominal by default) plus the
    payload on the end effector."""
    theta = (robot.theta if theta is None else np.asarray(theta, float)).copy()
    theta[robot.ee_slice] += payload_theta_in_end_effector(dumbbell, robot.extra["grasp_point"])
    return theta


_PD_MARGIN = 1e-3  # a drawn link keeps λ_min(pseudo-inertia) ≥ this share of its nominal one


def draw_robot_theta(
    robot: RobotModel,
    radius: np.ndarray,
    rng: np.random.Generator,
    *,
    mode: str = "drawn",
    link_theta: ArrayLike | None = None,
) -> np.ndarray:
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
    return parameter_radius(robot, ratio, ratio, floors=scenario.noise.theta_r_floor)


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


def real_robot_theta(
    robot: RobotModel, scenario: Scenario, seed: int
) -> tuple[np.ndarray, dict[str, np.ndarray] | None]:
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
    theta = draw_robot_theta(robot, _robot_parameter_box(robot, scenario), rng, mode=mode, link_theta=own)
    return theta, {
        name: own[i] + theta[10 * i : 10 * i + 10] - robot.theta[10 * i : 10 * i + 10]
        for i, name in enumerate(robot.body_names)
    }


def make_real_plant(
    robot: RobotModel, inertials: dict | None, time_step: float, *, builder: DiagramBuilder
) -> tuple[MultibodyPlant, SceneGraph, ModelInstanceIndex]:
    """make_plant of the model, or of a temporary copy of its URDF with the drawn inertials."""

    if inertials is None:
        return make_plant(robot.source, time_step=time_step, builder=builder)
    with tempfile.TemporaryDirectory(prefix="safesysid_real_arm_") as directory:
        return make_plant(
            _urdf_with_inertials(robot.source, inertials, directory), time_step=time_step, builder=builder
        )


@dataclass
class RealArm:
    """The real arm station: `system` is the sub-Diagram "real_arm" added to the caller's builder
    (as manipulation's MakeHardwareStation), the ports are its exported ones, and plant,
    scene_graph, instance, payload_body are handles into it (their contexts: from the root's)."""

    robot: RobotModel
    plant: MultibodyPlant
    scene_graph: SceneGraph
    instance: ModelInstanceIndex
    payload_body: RigidBody
    dumbbell: Dumbbell | None
    commanded_torque_input: InputPort  # (n)
    state_output: OutputPort  # (2n): encoders q, v
    measured_torque_output: OutputPort  # (n)
    applied_torque_output: OutputPort  # (n): torque reaching the joints (saturated, delayed)
    motor_torque_output: OutputPort  # (n): saturated command (what the sensor measures)
    torque_sensor: TorqueSensor
    time_step: float
    payload_collision: tuple[tuple[GeometryId, ProximityProperties], ...] = ()  # of the dumbbell
    robot_geometries: GeometrySet | None = None  # the arm + payload (no self-contact)
    theta: np.ndarray | None = None  # the robot's 14 n parameters the plant uses (no payload)
    system: Diagram | None = None  # the Diagram "real_arm"
    plant_state_output: OutputPort | None = None  # (2n): the plant's true q, v (not the encoders')
    query_output: OutputPort | None = None  # SceneGraph's QueryObject (true geometry)
    noise_source: RandomSource | None = None  # the torque sensor's noise (None: noiseless)
    seed: int = 0  # the run's seed: drawn parameters at build, sensor noise via seed_noise
    released_body: RigidBody | None = None  # free body taking the payload over at release (None: not releasable)
    transmission: LeafSystem | None = None  # ElasticTransmission (dynamic joint elasticity) or None
    # Injected faults (scenario `faults`, systems/plant/faults.py): the stages (their events), their
    # RandomSources (seeded with the noise), and the estimator's packet port when samples are faulty.
    fault_stages: tuple[LeafSystem, ...] = ()
    fault_sources: tuple[RandomSource, ...] = ()
    estimator_samples_output: OutputPort | None = None  # estimation.packets.packet_size(n), or None

    @property
    def n(self) -> int:
        return self.robot.n

    def plant_context(self, root_context: Context) -> Context:
        return self.plant.GetMyMutableContextFromRoot(root_context)

    def set_payload(self, root_context: Context, dumbbell: Dumbbell | None) -> None:
        """Grasp (a Dumbbell) or release (None) at run time."""

        ctx = self.plant_context(root_context)
        spatial = dumbbell_spatial_inertia(dumbbell) if dumbbell is not None else SpatialInertia.Zero()
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

    def payload_frame_name(self) -> str:
        """SceneGraph's scoped name of the welded payload's frame ('instance::body')."""
        frame = self.plant.GetBodyFrameIdOrThrow(self.payload_body.index())
        return self.scene_graph.model_inspector().GetName(frame)

    def payload_pose(self, root_context: Context) -> RigidTransform:
        """RigidTransform of the payload in the world: the released body once released, else the
        welded one (its frame: the dumbbell centre, x along the handle)."""

        ctx = self.plant_context(root_context)
        released = self.released_body is not None and not self.released_body.is_locked(ctx)
        return (self.released_body if released else self.payload_body).EvalPoseInWorld(ctx)

    def payload_speed(self, root_context: Context) -> float:
        """|v| of the payload centre in the world [m/s]."""

        ctx = self.plant_context(root_context)
        released = self.released_body is not None and not self.released_body.is_locked(ctx)
        body = self.released_body if released else self.payload_body
        return float(np.linalg.norm(body.EvalSpatialVelocityInWorld(ctx).translational()))

    def release(self, root_context: Context) -> RigidTransform:
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

    def seed_noise(self, root_context: Context, seed: int | None = None) -> None:
        """Seed the sensor noise of this context (the station's seed unless given): Drake's
        SetRandomContext(RandomGenerator(seed)) on the noise source only, so the rest of the
        context is kept. Unseeded, a RandomSource draws from a default seed of its own."""
        seed = int(self.seed if seed is None else seed)
        for k, source in enumerate((self.noise_source, *self.fault_sources)):
            if source is not None:  # a stream per source (k = 0: the sensor noise, as before)
                source.SetRandomContext(
                    source.GetMyMutableContextFromRoot(root_context), RandomGenerator(seed + 7919 * k)
                )

    def fault_events(self, root_context: Context) -> list[dict]:
        """[{t, kind, detail}] of the injected faults (scenario `faults`)."""
        return [e for stage in self.fault_stages for e in stage.events(stage.GetMyContextFromRoot(root_context))]

    def set_state(self, root_context: Context, q: ArrayLike, v: ArrayLike | None = None) -> None:
        ctx = self.plant_context(root_context)
        q, v = np.asarray(q, float), np.zeros(self.n) if v is None else np.asarray(v, float)
        self.plant.SetPositions(ctx, self.instance, q)
        self.plant.SetVelocities(ctx, self.instance, v)
        if self.transmission is not None:  # the springs carry the links' weight from the start
            weight = -self.plant.GetVelocitiesFromArray(self.instance, self.plant.CalcGravityGeneralizedForces(ctx))
            self.transmission.set_equilibrium(
                self.transmission.GetMyMutableContextFromRoot(root_context), q, v, link_torque=weight
            )
        if self.released_body is not None:  # waiting, locked, for a release
            self.plant.SetFreeBodyPose(ctx, self.released_body, PARKED)
            self.released_body.Lock(ctx)

    def true_theta(self, dumbbell: Dumbbell | str | None = "current") -> np.ndarray:
        return true_theta(self.robot, self.dumbbell if dumbbell == "current" else dumbbell, self.theta)


def dumbbell_spatial_inertia(db: Dumbbell) -> SpatialInertia:
    return inertial.to_spatial_inertia(db.theta_about_centre())


PARKED = RigidTransform([0.0, 0.0, -3.0])  # the released body's pose until the release: far below the floor


def register_dumbbell_geometry(
    plant: MultibodyPlant, body: RigidBody, db: Dumbbell, *, prefix: str = "dumbbell"
) -> None:
    along_x = RotationMatrix.MakeYRotation(np.pi / 2)  # Drake cylinders run along z
    friction = CoulombFriction(0.8, 0.6)
    for k, (_, x, radius, length) in enumerate(db.parts()):
        pose = RigidTransform(along_x, [x, 0.0, 0.0])
        name = f"{prefix}_{db.name}_{['handle', 'head_pos', 'head_neg'][k]}"
        plant.RegisterVisualGeometry(body, pose, Cylinder(radius, length), name + "_visual", [0.15, 0.15, 0.18, 1.0])
        plant.RegisterCollisionGeometry(body, pose, Cylinder(radius, length), name, friction)


def register_obstacles(plant: MultibodyPlant, scenario: Scenario) -> None:
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
