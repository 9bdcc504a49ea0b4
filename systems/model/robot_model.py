"""Robot model: one fixed-base arm, read once from a URDF/SDF and the joint-parameter YAML.

Everything above (plant, controller, planner, estimator, diagnosis) gets its kinematics,
nominal parameters, limits and friction from a RobotModel, so there is one source of truth.

Parameter vector theta (length 14 n), in this order everywhere:
    [theta_body_1 (10), ..., theta_body_n (10), friction_1 (4), ..., friction_n (4)]
body i = composite child of joint i (bodies welded to it merged), about its frame origin;
friction_j = [Fc, Fv, Ia, beta].
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.model import inertial, regressors
from safesysid.systems.model.regressors import KinematicTree

if TYPE_CHECKING:  # Drake is imported where a plant is built
    from pydrake.geometry import SceneGraph
    from pydrake.multibody.plant import MultibodyPlant
    from pydrake.multibody.tree import ModelInstanceIndex, RigidBody
    from pydrake.systems.framework import Context, DiagramBuilder

MODELS_DIR = Path(__file__).resolve().parents[2] / "models"  # systems/model/ -> the package root
FRICTION_NAMES = ("Fc", "Fv", "Ia", "beta")


class ModelError(ValueError):
    """Bad model input (file or field named in the message)."""


@dataclass
class JointParameters:
    """Limits and friction per joint (SI units; +-inf position limits for continuous joints)."""

    names: list[str]
    position_lower: np.ndarray
    position_upper: np.ndarray
    velocity_limit: np.ndarray
    torque_limit: np.ndarray
    coulomb: np.ndarray
    viscous: np.ndarray
    armature: np.ndarray
    offset: np.ndarray

    def friction_theta(self) -> np.ndarray:
        return np.stack([self.coulomb, self.viscous, self.armature, self.offset], -1).ravel()

    @property
    def continuous(self) -> np.ndarray:
        return ~np.isfinite(self.position_lower) & ~np.isfinite(self.position_upper)


@dataclass
class RobotModel:
    tree: KinematicTree
    joint_params: JointParameters
    theta: np.ndarray  # nominal 14 n parameters
    end_effector: int  # body index of the end effector (identified body)
    body_names: list[str]
    source: str = ""
    coulomb_smoothing: float = 0.0  # rad/s; 0 means sign(v)
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.tree.n

    # ---- parameter bookkeeping ---------------------------------------------------------------
    def body_slice(self, i: int) -> slice:
        return slice(10 * i, 10 * i + 10)

    @property
    def ee_slice(self) -> slice:
        return self.body_slice(self.end_effector)

    @property
    def theta_e(self) -> np.ndarray:
        return self.theta[self.ee_slice].copy()

    def rest_mask(self) -> np.ndarray:
        """Boolean mask of theta entries that are not the end effector's (theta_r)."""
        mask = np.ones(14 * self.n, bool)
        mask[self.ee_slice] = False
        return mask

    def with_theta(self, theta: ArrayLike) -> RobotModel:
        return replace(self, theta=np.asarray(theta, float).copy())

    def with_end_effector_theta(self, theta_e: ArrayLike) -> RobotModel:
        t = self.theta.copy()
        t[self.ee_slice] = theta_e
        return self.with_theta(t)

    def parameter_names(self) -> list[str]:
        names = [f"{b}.{p}" for b in self.body_names for p in inertial.NAMES]
        return names + [f"{j}.{f}" for j in self.joint_params.names for f in FRICTION_NAMES]

    # ---- regressors (inertial + friction columns) ---------------------------------------------
    def standard_regressor(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """W (N, n, 14n): W theta = M a + C v + g + F(v, a)."""
        return np.concatenate(
            [
                regressors.standard_regressor(self.tree, q, v, a),
                regressors.friction_columns(v, a=a, kind="standard", smoothing_velocity=self.coulomb_smoothing),
            ],
            -1,
        )

    def momentum_regressor(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Wm (N, n, 14n): Wm theta = (M + diag(Ia)) v."""
        return np.concatenate(
            [regressors.momentum_regressor(self.tree, q, v), regressors.friction_columns(v, kind="momentum")], -1
        )

    def momentum_rate_regressor(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Wc (N, n, 14n): Wc theta = C^T v - g - (Fc sgn v + Fv v + beta).

        With Ia carried in the momentum, d/dt (Wm theta) = Wc theta + tau along any motion.
        """
        return np.concatenate(
            [
                regressors.momentum_rate_regressor(self.tree, q, v),
                regressors.friction_columns(v, kind="rate", smoothing_velocity=self.coulomb_smoothing),
            ],
            -1,
        )

    def passivity_regressor(self, q: np.ndarray, v: np.ndarray, va: np.ndarray, aa: np.ndarray) -> np.ndarray:
        """Wp (N, n, 14n): Wp theta = M aa + C(q, v) va + g + F(va, aa) (controller form)."""
        return np.concatenate(
            [
                regressors.passivity_regressor(self.tree, q, v, va, aa),
                regressors.friction_columns(va, a=aa, kind="standard", smoothing_velocity=self.coulomb_smoothing),
            ],
            -1,
        )

    def inverse_dynamics(
        self, q: np.ndarray, v: np.ndarray, a: np.ndarray, *, theta: np.ndarray | None = None
    ) -> np.ndarray:
        theta = self.theta if theta is None else theta
        return self.standard_regressor(q, v, a) @ theta

    def mass_matrix(self, q: np.ndarray, theta: np.ndarray | None = None) -> np.ndarray:
        """(N, n, n) mass matrix including armature, from the momentum regressor."""
        theta = self.theta if theta is None else theta
        q = np.atleast_2d(q)
        eye = np.eye(self.n)
        cols = [self.momentum_regressor(q, np.broadcast_to(eye[k], q.shape)) @ theta for k in range(self.n)]
        return np.stack(cols, -1)

    def forward_kinematics(self, q: np.ndarray) -> regressors.Kinematics:
        return regressors.forward_kinematics(self.tree, q)


# ---- loading -----------------------------------------------------------------------------------
def load_joint_parameters(path: str | Path, joint_names: Sequence[str] | None = None) -> tuple[dict, JointParameters]:
    """Joint parameters from the YAML (see models/kinova_gen3_params.yaml)."""
    import yaml

    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
        j = doc["joints"]
        names = list(j["names"])
        n = len(names)

        def arr(key, default=None):
            if key not in j:
                if default is None:
                    raise ModelError(f"{path}: missing field joints.{key}")
                return np.full(n, default, float)
            val = np.asarray(j[key], float)
            if val.shape != (n,):
                raise ModelError(f"{path}: field joints.{key} has {val.size} values, expected {n}")
            return val

        params = JointParameters(
            names=names,
            position_lower=arr("position_lower_rad", -np.inf),
            position_upper=arr("position_upper_rad", np.inf),
            velocity_limit=arr("velocity_limit_rad_s"),
            torque_limit=arr("torque_limit_Nm"),
            coulomb=arr("coulomb_Nm", 0.0),
            viscous=arr("viscous_Nms_rad", 0.0),
            armature=arr("armature_kgm2", 0.0),
            offset=arr("offset_Nm", 0.0),
        )
    except (OSError, yaml.YAMLError, KeyError, TypeError) as err:
        raise ModelError(f"{path}: cannot read joint parameters ({err})") from err
    if joint_names is not None and list(joint_names) != names:
        raise ModelError(f"{path}: joints.names {names} do not match the model joints {list(joint_names)}")
    return doc, params


def make_plant(
    model_path: str | Path, *, time_step: float = 0.0, scene_graph: bool = False, builder: DiagramBuilder | None = None
) -> tuple[MultibodyPlant, SceneGraph | None, ModelInstanceIndex]:
    """Drake MultibodyPlant of a fixed-base arm (root welded to the world if it floats).

    Returns (plant, scene_graph or None, model_instance). With `builder`, the plant is added
    to it (not finalized, so callers may add bodies); otherwise it is finalized.
    """
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph, MultibodyPlant
    from pydrake.systems.framework import DiagramBuilder

    model_path = Path(model_path)
    if not model_path.is_file():
        raise ModelError(f"{model_path}: model file not found")
    sg = None
    if builder is not None or scene_graph:
        builder = builder or DiagramBuilder()
        plant, sg = AddMultibodyPlantSceneGraph(builder, time_step)
    else:
        plant = MultibodyPlant(time_step)
    try:
        (instance,) = Parser(plant).AddModels(str(model_path))
    except Exception as err:  # Drake raises RuntimeError with a multi-line text
        raise ModelError(f"{model_path}: the model does not load ({str(err).splitlines()[0]})") from err
    root = _root_body(plant, instance)
    if not any(j.child_body().index() == root.index() for j in _joints(plant, instance)):
        plant.WeldFrames(plant.world_frame(), root.body_frame())
    _add_missing_actuators(plant, instance, _urdf_effort_limits(model_path))
    return plant, sg, instance


def _urdf_effort_limits(model_path):
    """{joint: effort} from URDF <limit effort=...> (Drake keeps it only with a transmission)."""
    import xml.etree.ElementTree as ET

    if Path(model_path).suffix.lower() != ".urdf":
        return {}
    try:
        root = ET.parse(model_path).getroot()
    except ET.ParseError as err:
        raise ModelError(f"{model_path}: not valid XML ({err})") from err
    out = {}
    for joint in root.iter("joint"):
        limit = joint.find("limit")
        if limit is not None and limit.get("effort") is not None:
            out[joint.get("name")] = float(limit.get("effort"))
    return out


def _add_missing_actuators(plant, instance, efforts):
    """One actuator per 1-dof joint that has none, so the plant can be driven by torques."""
    actuated = {plant.get_joint_actuator(i).joint().index() for i in plant.GetJointActuatorIndices()}
    for joint in _joints(plant, instance):
        if joint.num_velocities() == 1 and joint.index() not in actuated:
            limit = efforts.get(joint.name(), np.inf)
            plant.AddJointActuator(f"{joint.name()}_actuator", joint, limit if limit > 0 else np.inf)


def _joints(plant, instance):
    return [plant.get_joint(i) for i in plant.GetJointIndices(instance)]


def _root_body(plant, instance):
    bodies = [plant.get_body(i) for i in plant.GetBodyIndices(instance)]
    children = {j.child_body().index() for j in _joints(plant, instance)}
    roots = [b for b in bodies if b.index() not in children]
    return roots[0]


def tree_from_plant(
    plant: MultibodyPlant, context: Context, joint_names: Sequence[str] | None = None
) -> tuple[KinematicTree, np.ndarray, list[str], list[str]]:
    """KinematicTree + composite body thetas + body names from a finalized plant."""
    from pydrake.multibody.tree import BodyIndex, PrismaticJoint, RevoluteJoint

    movable = [plant.get_joint(i) for i in plant.GetJointIndices() if plant.get_joint(i).num_velocities() == 1]
    if not movable:
        raise ModelError("no movable (revolute or prismatic) joint: nothing to identify")
    if joint_names is not None:
        by_name = {j.name(): j for j in movable}
        missing = [n for n in joint_names if n not in by_name]
        if missing:
            raise ModelError(f"joints {missing} are not 1-dof joints of the model")
        movable = [by_name[n] for n in joint_names]
    for j in movable:
        if not isinstance(j, (RevoluteJoint, PrismaticJoint)):
            raise ModelError(f"joint {j.name()}: only revolute and prismatic joints are supported")
    # Each body is carried by the nearest movable joint above it (through welds), or the world.
    child_of = {j.child_body().index(): k for k, j in enumerate(movable)}
    inboard = {
        plant.get_joint(i).child_body().index(): plant.get_joint(i).parent_body() for i in plant.GetJointIndices()
    }

    def carrier(body):
        while body.index() not in child_of:
            if body.index() not in inboard:  # the world, or a root welded to nothing
                return -1, plant.world_body()
            body = inboard[body.index()]
        return child_of[body.index()], body

    n = len(movable)
    parent = np.empty(n, int)
    x_pj = np.empty((n, 4, 4))
    x_jc = np.empty((n, 4, 4))
    axis = np.empty((n, 3))
    prismatic = np.zeros(n, bool)
    members = {k: [] for k in range(n)}
    for b in range(plant.num_bodies()):
        body = plant.get_body(BodyIndex(b))
        k, _ = carrier(body)
        if k >= 0:
            members[k].append(body.index())
    for k, j in enumerate(movable):
        par, carrier_body = carrier(j.parent_body())
        parent[k] = par
        x_cf = plant.CalcRelativeTransform(context, carrier_body.body_frame(), j.frame_on_parent())
        x_pj[k] = x_cf.GetAsMatrix4()
        x_jc[k] = j.frame_on_child().GetFixedPoseInBodyFrame().inverse().GetAsMatrix4()
        prismatic[k] = isinstance(j, PrismaticJoint)
        axis[k] = j.translation_axis() if prismatic[k] else j.revolute_axis()
    if np.any(parent >= np.arange(n)):
        raise ModelError("joints must be listed parents first")
    thetas = []
    for k, j in enumerate(movable):
        child = j.child_body()
        spatial = plant.CalcSpatialInertia(context, child.body_frame(), members[k])
        thetas.append(inertial.from_spatial_inertia(spatial))
    gravity = plant.gravity_field().gravity_vector()
    tree = KinematicTree(
        parent=parent,
        X_parent_joint=x_pj,
        X_joint_child=x_jc,
        axis=axis,
        prismatic=prismatic,
        gravity=np.asarray(gravity, float),
    )
    return tree, np.concatenate(thetas), [j.child_body().name() for j in movable], [j.name() for j in movable]


def joint_parameters_from_plant(plant: MultibodyPlant, joint_names: Sequence[str]) -> JointParameters:
    """Limits from the model file when no parameter YAML is given (friction zero)."""
    lo, hi, vel, eff = [], [], [], []
    for name in joint_names:
        j = plant.GetJointByName(name)
        lo.append(j.position_lower_limits()[0])
        hi.append(j.position_upper_limits()[0])
        vel.append(j.velocity_upper_limits()[0])
        act = [
            plant.get_joint_actuator(a)
            for a in plant.GetJointActuatorIndices()
            if plant.get_joint_actuator(a).joint().name() == name
        ]
        eff.append(act[0].effort_limit() if act else np.inf)
    z = np.zeros(len(joint_names))
    return JointParameters(
        list(joint_names), np.array(lo), np.array(hi), np.array(vel), np.array(eff), z, z.copy(), z.copy(), z.copy()
    )


def load_robot(
    *,
    model_path: str | Path | None = None,
    params_path: str | Path | None = None,
    coulomb_smoothing: float = 0.0,
    end_effector: str | None = None,
) -> RobotModel:
    """RobotModel from a URDF/SDF and (optionally) a joint-parameter YAML.

    With neither path, the project's Kinova Gen3 (models/kinova_gen3_params.yaml).
    """
    doc = None
    if model_path is None and params_path is None:
        params_path = MODELS_DIR / "kinova_gen3_params.yaml"
    if params_path is not None:
        doc, _ = load_joint_parameters(params_path)
        if model_path is None:
            model_path = Path(params_path).parent / doc["urdf"]
    plant, _, _ = make_plant(model_path)
    plant.Finalize()
    context = plant.CreateDefaultContext()
    names = None
    if doc is not None:
        names = doc["joints"]["names"]
    try:
        tree, theta_bodies, body_names, joint_names = tree_from_plant(plant, context, names)
    except ModelError as err:  # say which file
        raise ModelError(f"{model_path}: {err}") from err
    if params_path is not None:
        _, params = load_joint_parameters(params_path, joint_names)
    else:
        params = joint_parameters_from_plant(plant, joint_names)
    ee_name = end_effector or (doc or {}).get("end_effector_link")
    ee, x_carrier_ee = _end_effector(plant, context, body_names, ee_name, params_path or model_path)
    theta = np.concatenate([theta_bodies, params.friction_theta()])
    grasp = np.asarray((doc or {}).get("grasp_point_m", [0, 0, 0]), float)
    if x_carrier_ee is not None:  # given in the frame of a link welded to the end-effector body
        grasp = x_carrier_ee @ grasp
    extra = {"grasp_point": grasp, "params_doc": doc, "params_path": str(params_path or "")}
    return RobotModel(
        tree=tree,
        joint_params=params,
        theta=theta,
        end_effector=ee,
        body_names=body_names,
        source=str(model_path),
        coulomb_smoothing=coulomb_smoothing,
        extra=extra,
    )


def _end_effector(plant, context, body_names, ee_name, where):
    """(tree index, RigidTransform of the named link in that body's frame) of the end effector: a
    moving body, or a link welded to one (a hand on the flange: it is part of that body, and
    grasp_point_m, given in its frame, is moved into the body's frame; None for a moving body).
    No name: the last body."""
    if ee_name is None:
        return len(body_names) - 1, None
    if ee_name in body_names:
        return body_names.index(ee_name), None
    index = carrier_index(plant, plant.GetBodyByName(ee_name), body_names) if plant.HasBodyNamed(ee_name) else -1
    if index < 0:
        raise ModelError(f"{where}: end_effector_link: {ee_name!r} is not a moving body of the model nor welded to one")
    carrier = plant.GetBodyByName(body_names[index])
    return index, plant.CalcRelativeTransform(context, carrier.body_frame(), plant.GetBodyByName(ee_name).body_frame())


def carrier_index(plant: MultibodyPlant, body: RigidBody, body_names: Sequence[str]) -> int:
    """Tree index (in `body_names`) of the body that carries `body`: itself or the nearest body
    above it through welds; -1 when it is welded to the world (it never moves)."""
    inboard = {plant.get_joint(j).child_body().index(): plant.get_joint(j) for j in plant.GetJointIndices()}
    while body.name() not in body_names and body.index() in inboard:
        body = inboard[body.index()].parent_body()
    return body_names.index(body.name()) if body.name() in body_names else -1
