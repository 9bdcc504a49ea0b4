"""Scenario schema (typed dataclasses loaded with Drake's yaml_load_typed) and loader.

Every constant a system uses comes from here, the unit in the field name (_m, _s, _rad, _Nm,
_kg ...) or the docstring. Paths inside a scenario are relative to the scenario file; the
prefix `builtin:` names a file in the package's models/ folder.
"""

import dataclasses as dc
import typing
from pathlib import Path

import numpy as np

from safesysid.systems.uncertainty import ParameterFloors
from safesysid.systems.robot_model import MODELS_DIR

SCENARIOS_DIR = Path(__file__).resolve().parent.parent / "scenarios"
List = typing.List
Optional = typing.Optional


MAX_CONTROL_STEP_S = 0.001


class ScenarioError(ValueError):
    """Bad scenario input; the message names the file and the field."""


@dc.dataclass
class Robot:
    params: str = "builtin:kinova_gen3_params.yaml"  # joint parameters YAML (names the URDF)
    model: str = ""  # URDF/SDF; empty: the one named in `params`
    coulomb_smoothing_rad_s: float = 0.01  # Coulomb law Fc*tanh(v/vs); 0 = sign(v)


@dc.dataclass
class Payload:
    dumbbell: str = "4lb"  # key of models/dumbbells.yaml, or "none"
    dumbbells_file: str = "builtin:dumbbells.yaml"


@dc.dataclass
class Obstacle:
    """Oriented box: centre, roll-pitch-yaw and full side lengths, in the robot base frame."""

    name: str = "box"
    xyz_m: List[float] = dc.field(default_factory=lambda: [0.5, 0.0, 0.2])
    rpy_rad: List[float] = dc.field(default_factory=lambda: [0.0, 0.0, 0.0])
    size_m: List[float] = dc.field(default_factory=lambda: [0.1, 0.1, 0.1])


@dc.dataclass
class Noise:
    """Measurement model: |tau_meas - tau| <= ratio*|tau| + floor per sample and joint."""

    torque_ratio: float = 0.025
    torque_floor_Nm: float = 0.0
    distribution: str = "uniform"  # uniform inside the declared bound | none
    # Declared bound the estimator uses (may differ from the simulated noise, to test).
    declared_torque_ratio: float = 0.025
    declared_torque_floor_Nm: float = 0.05
    theta_r_ratio: float = 0.05  # relative uncertainty of the rest-of-robot parameters
    # Absolute floor of each robot parameter's half-width, per kind (units in the names): the box
    # is nominal +- max(theta_r_ratio |nominal|, floor), shared by controller, planner, estimator
    # and the drawn real arm (systems/armour.py ParameterFloors has the defaults).
    theta_r_floor: ParameterFloors = dc.field(default_factory=ParameterFloors)


@dc.dataclass
class PlantEffects:
    """Effects the models above the plant do not know (all off by default)."""

    torque_sensor_offset_Nm: List[float] = dc.field(default_factory=list)
    torque_sensor_scale: List[float] = dc.field(default_factory=list)
    time_delay_s: float = 0.0
    torque_sensor_lag_s: float = 0.0  # first-order low-pass of the torque sensor signal
    base_tilt_rad: List[float] = dc.field(default_factory=lambda: [0.0, 0.0])
    joint_stiffness_Nm_rad: List[float] = dc.field(default_factory=list)


@dc.dataclass
class Plant:
    time_step_s: float = 0.001
    # The real arm's robot parameters (links, friction, armature, offsets): the model's nominal
    # values, drawn uniformly inside the declared box (seeded; links kept physically consistent),
    # or at a random vertex of it (pulled inside where a vertex is not physically consistent).
    robot_parameters: str = "nominal"  # nominal | drawn | corner
    effects: PlantEffects = dc.field(default_factory=PlantEffects)


@dc.dataclass
class Controller:
    """ARMOUR robust passivity controller (reference-notes.md)."""

    Kr: List[float] = dc.field(default_factory=lambda: [5.0, 5.0, 5.0, 5.0, 7.0, 7.0, 7.0])
    alpha: float = 20.0
    # Lyapunov level of the tube [J]. The hardware value 0.02 gives eps = 0.072 and, with the
    # Table II prior, no certified torque margin on the 45 N m wrist joints at most poses (the
    # planner refuses to move); 0.005 halves eps (|e| <= 0.0072 rad at Kr = 5) and plans start.
    V_max: float = 0.005
    kind: str = "armour"  # armour | pid | adaptive | adaptive_robust
    # Baselines (systems/controller_systems.py), per joint; Gen3 inertia with armature is ~9-14 kg m^2,
    # so Kp ~ M (10 rad/s)^2 and Kd ~ 2 M 10 rad/s.
    pid_kp_Nm_rad: List[float] = dc.field(default_factory=lambda: [1000.0] * 7)
    pid_ki_Nm_rad_s: List[float] = dc.field(default_factory=lambda: [1000.0] * 7)
    pid_kd_Nms_rad: List[float] = dc.field(default_factory=lambda: [180.0] * 7)
    adaptive_kd_Nms_rad: List[float] = dc.field(default_factory=lambda: [100.0] * 7)
    # Adaptation gain per end-effector parameter [m, m c (3), I (6)] (units of theta_e^2 / (N m rad)).
    adaptive_gamma: List[float] = dc.field(default_factory=lambda: [5.0, 1.0, 1.0, 1.0, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1])
    adaptive_boundary_rad_s: float = 0.05  # boundary layer of the adaptive robust (adap-2) term


@dc.dataclass
class Planner:
    duration_s: float = 3.0  # t_f
    replan_period_s: float = 1.5  # t_p
    num_plans: int = 4
    k_center_rad: List[float] = dc.field(default_factory=lambda: [0.0] * 7)
    k_range_rad: List[float] = dc.field(default_factory=lambda: [np.pi / 48] * 4 + [np.pi / 20] * 3)
    num_time_intervals: int = 128  # reachability over-approximation
    num_cost_samples: int = 128  # N_s of the exciting cost
    cost: str = "exciting"  # exciting | goal | random
    goal_q_rad: List[float] = dc.field(default_factory=list)
    solver: str = "ipopt"  # ipopt | snopt
    max_solve_time_s: float = 1.2  # wall cap inside t_p
    max_iterations: int = 100
    floor_z_m: float = 0.0  # floor plane height (an obstacle)


@dc.dataclass
class Estimator:
    horizon_s: float = 0.1  # segment length h
    integration: str = "trapezoid"  # trapezoid | euler (paper)
    solver: str = "ipopt"  # ipopt | snopt
    max_gap_s: float = 0.05  # a segment never spans a time step longer than this
    set_membership: str = "mass"  # LP refinement of [θ_e]: none | mass | all (estimator.py)
    point_estimate: str = "map"  # θ0: map (θ_r marginalised) | paper (plain least squares)
    # Logged torque: held (zero-order hold, exact left sum) | continuous (trapezoid + rate bound).
    torque_signal: str = "held"
    hold_period_s: float = 0.0  # held: the hold period; 0 = plant.time_step_s
    torque_rate_limit_Nm_s: float = 200.0  # continuous: declared |dtau/dt|, checked on the data
    quadrature_safety: float = 2.0  # kappa of the quadrature bound (estimator.py), >= 2


@dc.dataclass
class InitialInterval:
    """End-effector prior (paper Table II): nominal and box, theta order of contracts.md."""

    nominal: List[float] = dc.field(default_factory=lambda: [3.2, 0.0, 0.0, -0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    lower: List[float] = dc.field(default_factory=lambda: [1.2, -0.4, -0.4, -1.0] + [-0.2] * 6)
    upper: List[float] = dc.field(default_factory=lambda: [5.2, 0.4, 0.4, -0.1] + [0.2] * 6)


@dc.dataclass
class Task:
    """Task phase (paper §VII): after identification the arm follows a trajectory computed
    offline (systems/task_trajectory.py) from q0_rad to a goal, then releases the payload.

    Goal: `goal_q_rad` (a joint configuration) or a placement: the payload (dumbbell) centre at
    `place_xyz_m`, handle horizontal, gripper vertical (Drake InverseKinematics, then free in the
    optimization); with neither, the centre goes above the top centre of the obstacle named
    `platform` so that its lowest point is `release_height_m` above it. No goal, no platform:
    no task phase.
    """

    goal_q_rad: List[float] = dc.field(default_factory=list)
    place_xyz_m: List[float] = dc.field(default_factory=list)  # payload centre target, base frame
    platform: str = ""  # name of the obstacle (in `obstacles`) the payload is placed on
    release_height_m: float = 0.03  # payload's lowest point above the platform top at release
    placement_tolerance_m: float = 0.01  # success: |payload centre at release - target|
    duration_s: float = 2.0  # paper: 2 s
    num_pieces: int = 2  # degree-5 Bézier pieces of equal length, C2 at the junctions
    payload_model: str = "8lb"  # dumbbell whose model the trajectory is computed with
    collision_samples: int = 200  # sphere/obstacle checks (+ a margin for the motion in between)
    torque_samples: int = 41  # inverse-dynamics checks
    torque_margin_ratio: float = 0.2  # nominal torque <= (1 - ratio) * limit (room for the tube)
    solver: str = "snopt"  # snopt (Ipopt as fallback) | ipopt
    max_iterations: int = 500
    max_solve_time_s: float = 120.0  # wall-time cap per solver (offline; the result is cached)


@dc.dataclass
class Scenario:
    name: str = "scenario"
    robot: Robot = dc.field(default_factory=Robot)
    q0_rad: List[float] = dc.field(default_factory=lambda: [0.0, 0.26, 0.0, 2.0, 0.0, 0.9, 1.57])
    payload: Payload = dc.field(default_factory=Payload)
    obstacles: List[Obstacle] = dc.field(default_factory=list)
    noise: Noise = dc.field(default_factory=Noise)
    plant: Plant = dc.field(default_factory=Plant)
    controller: Controller = dc.field(default_factory=Controller)
    planner: Planner = dc.field(default_factory=Planner)
    estimator: Estimator = dc.field(default_factory=Estimator)
    initial_interval: InitialInterval = dc.field(default_factory=InitialInterval)
    task: Task = dc.field(default_factory=Task)
    method: str = "ours"  # ours | random | conservative | wrong
    seed: int = 0
    # Where the loader found the file (not a YAML field).
    source: str = ""


METHODS = ("ours", "random", "conservative", "wrong")
_CHOICES = {
    "method": METHODS,
    "planner.cost": ("exciting", "goal", "random"),
    "planner.solver": ("ipopt", "snopt"),
    "estimator.solver": ("ipopt", "snopt"),
    "estimator.integration": ("trapezoid", "euler"),
    "estimator.set_membership": ("none", "mass", "all"),
    "estimator.point_estimate": ("map", "paper"),
    "estimator.torque_signal": ("held", "continuous"),
    "plant.robot_parameters": ("nominal", "drawn", "corner"),
    "noise.distribution": ("uniform", "none"),
    "controller.kind": ("armour", "pid", "adaptive", "adaptive_robust"),
    "task.solver": ("snopt", "ipopt"),
}


def _check(value, schema, path, errors):
    """Walk raw YAML against the dataclass schema, collecting 'key.path: problem' strings."""
    origin = typing.get_origin(schema)
    if dc.is_dataclass(schema):
        if not isinstance(value, dict):
            errors.append(f"{path or 'top level'}: expected a mapping")
            return
        fields = {f.name: f for f in dc.fields(schema) if f.name != "source"}
        for key, item in value.items():
            sub = f"{path}.{key}" if path else str(key)
            if key not in fields:
                errors.append(f"{sub}: unknown key (known: {', '.join(fields)})")
            else:
                _check(item, typing.get_type_hints(schema)[key], sub, errors)
    elif origin in (list, List):
        if not isinstance(value, list):
            errors.append(f"{path}: expected a list")
            return
        (inner,) = typing.get_args(schema)
        for k, item in enumerate(value):
            _check(item, inner, f"{path}[{k}]", errors)
    elif origin is typing.Union:
        inner = [a for a in typing.get_args(schema) if a is not type(None)][0]
        if value is not None:
            _check(value, inner, path, errors)
    elif schema is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            errors.append(f"{path}: expected a number, got {value!r}")
    elif schema is int:
        if isinstance(value, bool) or not isinstance(value, int):
            errors.append(f"{path}: expected an integer, got {value!r}")
    elif schema is str:
        if not isinstance(value, str):
            errors.append(f"{path}: expected a string, got {value!r}")
    elif schema is bool and not isinstance(value, bool):
        errors.append(f"{path}: expected true/false, got {value!r}")


def resolve_path(text, base_dir):
    """`builtin:NAME` -> models/NAME; relative paths against the scenario's folder."""
    if text.startswith("builtin:"):
        return MODELS_DIR / text[len("builtin:"):]
    p = Path(text).expanduser()
    return p if p.is_absolute() else Path(base_dir) / p


def _validate(s: Scenario, where):
    def need(cond, field, msg):
        if not cond:
            raise ScenarioError(f"{where}: {field}: {msg}")

    for key, allowed in _CHOICES.items():
        obj = s
        for part in key.split("."):
            obj = getattr(obj, part)
        need(obj in allowed, key, f"{obj!r} is not one of {', '.join(allowed)}")
    need(len(s.q0_rad) == 7 or len(s.q0_rad) > 0, "q0_rad", "must list one angle per joint")
    for k, ob in enumerate(s.obstacles):
        need(len(ob.xyz_m) == 3, f"obstacles[{k}].xyz_m", "needs 3 values")
        need(len(ob.rpy_rad) == 3, f"obstacles[{k}].rpy_rad", "needs 3 values")
        need(len(ob.size_m) == 3 and min(ob.size_m) > 0, f"obstacles[{k}].size_m", "needs 3 positive values")
    ii = s.initial_interval
    for name in ("nominal", "lower", "upper"):
        need(len(getattr(ii, name)) == 10, f"initial_interval.{name}", "needs 10 values")
    need(np.all(np.array(ii.lower) <= np.array(ii.nominal)) and np.all(np.array(ii.nominal) <= np.array(ii.upper)),
         "initial_interval", "needs lower <= nominal <= upper")
    # The tube's invariance is argued and measured for a controller step of at most 1 ms
    # (systems/armour.py "Sampling"; docs/guarantees.md).
    need(0 < s.plant.time_step_s <= MAX_CONTROL_STEP_S, "plant.time_step_s",
         f"must be in (0, {MAX_CONTROL_STEP_S}] s (the tracking guarantee assumes a >= 1 kHz controller)")
    need(s.plant.effects.time_delay_s >= 0, "plant.effects.time_delay_s", "must be >= 0")
    need(s.plant.effects.torque_sensor_lag_s >= 0, "plant.effects.torque_sensor_lag_s", "must be >= 0")
    need(s.estimator.horizon_s > 0, "estimator.horizon_s", "must be > 0")
    need(s.estimator.quadrature_safety >= 2, "estimator.quadrature_safety", "must be >= 2")
    need(s.estimator.hold_period_s >= 0, "estimator.hold_period_s", "must be >= 0")
    need(s.estimator.torque_rate_limit_Nm_s > 0, "estimator.torque_rate_limit_Nm_s", "must be > 0")
    for key, value in dc.asdict(s.noise.theta_r_floor).items():
        need(value >= 0, f"noise.theta_r_floor.{key}", "must be >= 0")
    need(0 < s.planner.replan_period_s <= s.planner.duration_s, "planner.replan_period_s", "must be in (0, duration_s]")
    need(s.noise.torque_ratio >= 0 and s.noise.declared_torque_ratio >= 0, "noise", "ratios must be >= 0")
    for field, text in (("robot.params", s.robot.params), ("payload.dumbbells_file", s.payload.dumbbells_file)):
        need(resolve_path(text, Path(where).parent).is_file(), field, f"file {text!r} not found")
    if s.robot.model:
        need(resolve_path(s.robot.model, Path(where).parent).is_file(), "robot.model", f"file {s.robot.model!r} not found")
    _validate_task(s, need, where)
    if s.payload.dumbbell.lower() != "none":
        from safesysid.systems.payload import load_dumbbells

        names = list(load_dumbbells(resolve_path(s.payload.dumbbells_file, Path(where).parent)))
        need(s.payload.dumbbell in names, "payload.dumbbell", f"{s.payload.dumbbell!r} is not one of none, {', '.join(names)}")


def _validate_task(s: Scenario, need, where):
    t = s.task
    need(len(t.goal_q_rad) in (0, len(s.q0_rad)), "task.goal_q_rad", f"needs {len(s.q0_rad)} angles or none")
    need(len(t.place_xyz_m) in (0, 3), "task.place_xyz_m", "needs 3 values or none")
    need(not (t.goal_q_rad and t.place_xyz_m), "task", "give goal_q_rad or place_xyz_m, not both")
    names = [ob.name for ob in s.obstacles]
    need(not t.platform or t.platform in names, "task.platform", f"{t.platform!r} is not an obstacle name ({', '.join(names) or 'none'})")
    need(t.release_height_m >= 0, "task.release_height_m", "must be >= 0")
    need(t.placement_tolerance_m > 0, "task.placement_tolerance_m", "must be > 0")
    need(t.duration_s > 0, "task.duration_s", "must be > 0")
    need(t.num_pieces >= 1, "task.num_pieces", "must be >= 1")
    need(t.collision_samples >= 2, "task.collision_samples", "must be >= 2")
    need(t.torque_samples >= 2, "task.torque_samples", "must be >= 2")
    need(0 <= t.torque_margin_ratio < 1, "task.torque_margin_ratio", "must be in [0, 1)")
    need(t.max_iterations >= 1, "task.max_iterations", "must be >= 1")
    need(t.max_solve_time_s > 0, "task.max_solve_time_s", "must be > 0")
    if task_enabled(s):
        from safesysid.systems.payload import load_dumbbells

        names = list(load_dumbbells(resolve_path(s.payload.dumbbells_file, Path(where).parent)))
        need(t.payload_model in names, "task.payload_model", f"{t.payload_model!r} is not one of {', '.join(names)}")


def task_enabled(s: Scenario):
    """The scenario has a task phase (a goal or a platform)."""
    return bool(s.task.goal_q_rad or s.task.place_xyz_m or s.task.platform)


def load_scenario(path=None, text=None, overrides=None) -> Scenario:
    """Scenario from a YAML file (or text); raises ScenarioError naming file and key."""
    import yaml
    from pydrake.common.yaml import yaml_load_typed

    where = str(path) if path is not None else "<built-in defaults>"
    if path is not None:
        try:
            text = Path(path).read_text()
        except OSError as err:
            raise ScenarioError(f"{path}: cannot read scenario ({err.strerror})") from err
    text = text or "{}"
    try:
        raw = yaml.safe_load(text) or {}
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        line = f" line {mark.line + 1}" if mark else ""
        raise ScenarioError(f"{where}:{line} invalid YAML ({getattr(err, 'problem', err)})") from err
    raw.update(overrides or {})
    errors = []
    _check(raw, Scenario, "", errors)
    if errors:
        raise ScenarioError(f"{where}: {errors[0]}")
    scenario = yaml_load_typed(schema=Scenario, data=yaml.safe_dump(raw) if raw else "{}")
    scenario.source = str(Path(path).resolve()) if path is not None else str(SCENARIOS_DIR / "defaults")
    _validate(scenario, where if path is not None else str(SCENARIOS_DIR / "defaults.yaml"))
    return scenario


def scenario_dir(s: Scenario):
    return Path(s.source).parent


def robot_from_scenario(s: Scenario):
    """The RobotModel a scenario names (one source of truth for every system)."""
    from safesysid.systems.robot_model import load_robot

    base = scenario_dir(s)
    model = resolve_path(s.robot.model, base) if s.robot.model else None
    return load_robot(model, resolve_path(s.robot.params, base), coulomb_smoothing=s.robot.coulomb_smoothing_rad_s)
