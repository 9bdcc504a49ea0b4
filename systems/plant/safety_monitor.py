"""SafetyMonitor: the referee of a closed-loop run, on the TRUE geometry and state.

At every plant step it records the smallest signed distance between any robot geometry (the
link shapes of the model file and the payload, as SceneGraph holds them) and any anchored
environment geometry (obstacles, floor) from Drake's QueryObject, and the ratios of
|q| to the position limits, |v| to the velocity limits and |u| to the torque limits. It knows
nothing of the planner's spheres or over-approximations, so it can catch them being wrong.

SceneGraph filters the pairs of bodies welded together, the base and the world included, so the
base's pairs with the environment are queried one by one (a box through the base is a
collision); the base standing on its support (the floor) is not.

Torque is read twice: the controller's command (before the actuator saturation: this is what
the planner's torque bound certifies, and it may exceed the limit) and the motor torque after
saturation (what reaches the joints, never above the limit).

Bodies passed as `ignore_bodies` are neither robot nor environment: the released payload of the
task phase (systems/plant/station.py), which is meant to touch the platform once let go (before the
release it waits locked far below the floor, and the arm carries the welded payload, which the
monitor does check).

The record lives in the Context (abstract state, appended by a periodic unrestricted update at
t_k, which sees the state and inputs of t_k as a logger does): `record(context)`. With
period_s None it records nothing itself: `judge_log` judges a logged run afterwards, sample by
sample on the same geometry (a 1 kHz wall-clock loop must not spend its time on the referee).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from pydrake.common.value import AbstractValue
from pydrake.geometry import QueryObject
from pydrake.systems.framework import Context, EventStatus, LeafSystem

if TYPE_CHECKING:
    from safesysid.systems.plant.arm_plant import RealArm


@dataclass
class SafetyRecord:
    """One entry per sample in each list."""

    times: list[float] = field(default_factory=list)
    clearance: list[float] = field(default_factory=list)  # min signed distance [m]
    joint_ratio: list[float] = field(default_factory=list)  # max over joints of limit usage (1 = at limit)
    velocity_ratio: list[float] = field(default_factory=list)
    torque_ratio: list[float] = field(default_factory=list)  # motor torque (after saturation)
    commanded_ratio: list[float] = field(default_factory=list)  # controller command (before saturation)
    closest_pair: list[tuple[str, str] | None] = field(default_factory=list)

    def summary(self) -> dict:
        arr = lambda x: np.asarray(x, float) if x else np.zeros(1)  # noqa: E731
        clearance = arr(self.clearance)
        return {
            "min_clearance_m": float(clearance.min()),
            "collisions": int(np.sum(np.diff(np.r_[0, (clearance < 0).astype(int)]) == 1)),
            "max_joint_limit_ratio": float(arr(self.joint_ratio).max()),
            "max_velocity_ratio": float(arr(self.velocity_ratio).max()),
            "max_torque_ratio": float(arr(self.torque_ratio).max()),
            "max_commanded_torque_ratio": float(arr(self.commanded_ratio).max()),
        }


@dataclass(frozen=True)
class _Samples:
    """The monitor's abstract state: a persistent list of sample tuples (newest first), so
    appending one at each step copies nothing; immutable, so Drake's state copies share it."""

    head: tuple = ()  # (sample, rest) or ()

    def __deepcopy__(self, memo):
        return self

    def record(self) -> SafetyRecord:
        rows, node = [], self.head
        while node:
            rows.append(node[0])
            node = node[1]
        columns = zip(*reversed(rows)) if rows else [[] for _ in fields(SafetyRecord)]
        return SafetyRecord(*(list(c) for c in columns))


def limit_ratio(x: ArrayLike, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Per-sample max over joints of how far x is into [lower, upper] from the centre (1 = at a limit)."""
    finite = np.isfinite(lower) & np.isfinite(upper)
    if not finite.any():
        return np.zeros(np.shape(x)[:-1])
    lo, hi = lower[finite], upper[finite]
    return np.max(np.abs((np.asarray(x)[..., finite] - 0.5 * (lo + hi)) / (0.5 * (hi - lo))), axis=-1)


class SafetyMonitor(LeafSystem):
    """Inputs: geometry query, plant state (q, v), applied (motor) torque, commanded torque.
    Records every `period_s` (None: never; `judge_log`)."""

    def __init__(
        self, plant, scene_graph, robot, period_s, *, max_distance_m=0.5, supports=("floor",), ignore_bodies=()
    ):
        """supports: names of environment geometries the fixed base stands on (not collisions);
        ignore_bodies: bodies whose geometry takes no part (module docstring)."""
        super().__init__()
        self._robot = robot
        self._inspector = scene_graph.model_inspector()
        self._world = plant.GetBodyFrameIdOrThrow(plant.world_body().index())
        self._ignored = {plant.GetBodyFrameIdOrThrow(b.index()) for b in ignore_bodies}
        self._max_distance = max_distance_m
        self._fixed_pairs = self._base_environment_pairs(plant, set(supports))
        # Geometry classes as id sets, so the per-step filter does no inspector calls.
        from pydrake.geometry import Role

        ids = self._inspector.GetAllGeometryIds(Role.kProximity)
        self._environment_ids = frozenset(g for g in ids if self._is_environment(g))
        self._ignored_ids = frozenset(g for g in ids if self._inspector.GetFrameId(g) in self._ignored)
        n = robot.n
        self.query_port = self.DeclareAbstractInputPort("query", AbstractValue.Make(QueryObject()))
        self.state_port = self.DeclareVectorInputPort("state", 2 * n)
        self.torque_port = self.DeclareVectorInputPort("applied_torque", n)
        self.command_port = self.DeclareVectorInputPort("commanded_torque", n)
        self._samples = self.DeclareAbstractState(AbstractValue.Make(_Samples()))
        self.DeclareInitializationUnrestrictedUpdateEvent(self._clear)
        if period_s is not None:
            self.DeclarePeriodicUnrestrictedUpdateEvent(period_s, 0.0, self._record)

    def record(self, context: Context) -> SafetyRecord:
        """Every sample of the run so far (this system's context)."""
        return context.get_abstract_state(int(self._samples)).get_value().record()

    def _is_environment(self, geometry_id):
        return self._inspector.GetFrameId(geometry_id) == self._world

    def _base_environment_pairs(self, plant, supports):
        """(robot geometry on a body welded to the world, environment geometry) pairs, which the
        pairwise query never reports (SceneGraph filters welded bodies), supports excepted."""
        from pydrake.geometry import Role

        inspector = self._inspector
        ids = inspector.GetAllGeometryIds(Role.kProximity)
        environment = [g for g in ids if self._is_environment(g) and inspector.GetName(g) not in supports]
        fixed = [
            g
            for g in ids
            if not self._is_environment(g) and plant.IsAnchored(plant.GetBodyFromFrameId(inspector.GetFrameId(g)))
        ]
        return [(a, b) for a in fixed for b in environment]

    def min_clearance(self, query: QueryObject) -> tuple[float, tuple[str, str] | None]:
        distances = list(query.ComputeSignedDistancePairwiseClosestPoints(self._max_distance))
        distances += [query.ComputeSignedDistancePairClosestPoints(a, b) for a, b in self._fixed_pairs]
        best, closest = self._max_distance, None
        environment, ignored = self._environment_ids, self._ignored_ids
        for d in distances:
            if d.distance < best and ((d.id_A in environment) != (d.id_B in environment)):
                if not (d.id_A in ignored or d.id_B in ignored):
                    best, closest = d.distance, d
        if closest is None:
            return self._max_distance, None
        return best, (self._inspector.GetName(closest.id_A), self._inspector.GetName(closest.id_B))

    def measure(self, context: Context) -> tuple:
        """One sample (t, clearance, joint, velocity, torque and command ratios, closest pair),
        in SafetyRecord's field order."""
        return self.judge(
            context.get_time(),
            self.query_port.Eval(context),
            self.state_port.Eval(context),
            self.torque_port.Eval(context),
            self.command_port.Eval(context),
        )

    def judge(self, t: float, query: QueryObject, x: np.ndarray, u: np.ndarray, command: np.ndarray) -> tuple:
        """`measure` of given values: the geometry in `query`, state x, motor torque u, command."""
        jp = self._robot.joint_params
        n = self._robot.n
        clearance, pair = self.min_clearance(query)
        return (
            t,
            clearance,
            float(limit_ratio(x[:n], jp.position_lower, jp.position_upper)),
            float(np.max(np.abs(x[n:]) / jp.velocity_limit)),
            float(np.max(np.abs(u) / jp.torque_limit)),
            float(np.max(np.abs(command) / jp.torque_limit)),
            pair,
        )

    def _clear(self, context, state):
        state.get_mutable_abstract_state(int(self._samples)).set_value(_Samples())
        return EventStatus.Succeeded()

    def _record(self, context, state):
        old = context.get_abstract_state(int(self._samples)).get_value()
        state.get_mutable_abstract_state(int(self._samples)).set_value(_Samples((self.measure(context), old.head)))
        return EventStatus.Succeeded()


def judge_log(
    monitor: SafetyMonitor, arm: RealArm, root_context: Context, log: dict, *, released_at: float | None = None
) -> SafetyRecord:
    """The record of a logged run of `arm` (a RealArm): log's "state" (the arm's true q, v),
    "motor_torque", "command" (arrays, one row per sample) and "t". Each sample's geometry is set
    in root_context (a context of the arm's diagram used for nothing else). The arm's joints only:
    the payload is welded to it until released_at (then emptied, as RealArm.release does: no
    collision role), and a released payload is the monitor's ignore_bodies."""
    plant_context = arm.plant.GetMyMutableContextFromRoot(root_context)
    monitor_context = monitor.GetMyContextFromRoot(root_context)
    rows, held = [], arm.dumbbell is not None
    for i, t in enumerate(log["t"]):
        if held and released_at is not None and t >= released_at:
            arm.set_payload(root_context, None)
            held = False
        arm.plant.SetPositionsAndVelocities(plant_context, arm.instance, log["state"][i])
        query = monitor.query_port.Eval(monitor_context)
        rows.append(monitor.judge(float(t), query, log["state"][i], log["motor_torque"][i], log["command"][i]))
    columns = zip(*rows) if rows else [[] for _ in fields(SafetyRecord)]
    return SafetyRecord(*(list(c) for c in columns))
