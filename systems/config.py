"""The scenario schema: typed dataclasses that Drake's yaml_load_typed reads (app/scenario.py loads,
layers and validates them), and the few helpers that interpret their fields.

Every constant a system uses comes from here, the unit in the field name (_m, _s, _rad, _Nm,
_kg ...) or the docstring. Paths inside a scenario are relative to the scenario file; the
prefix `builtin:` names a file in the package's models/ folder.

No `from __future__ import annotations` here: Drake's yaml loader reads the field types, and
cannot resolve string annotations.
"""

import dataclasses as dc
import typing
from pathlib import Path

import numpy as np

from .robot_model import MODELS_DIR

List = list
Optional = typing.Optional

MAX_CONTROL_STEP_S = 0.001
METHODS = ("ours", "random", "conservative", "wrong")


class ScenarioError(ValueError):
    """Bad scenario input; the message names the file and the field."""


@dc.dataclass
class ParameterFloors:
    """Absolute floor of the half-width of each robot parameter in [theta], per kind (SI units in
    the names): the box is nominal +- max(ratio |nominal|, floor), so parameters whose nominal is
    zero (torque offsets beta, products of inertia, some first moments) are uncertain too."""

    mass_kg: float = 0.01
    first_moment_kgm: float = 0.0005
    inertia_kgm2: float = 5e-5
    coulomb_Nm: float = 0.01
    viscous_Nms_rad: float = 0.01
    armature_kgm2: float = 0.01
    offset_Nm: float = 0.05

    def per_parameter(self, n):
        """(14 n,) floors in theta order: per body [m, m c (3), I (6)], per joint [Fc, Fv, Ia, beta]."""
        body = [self.mass_kg] + [self.first_moment_kgm] * 3 + [self.inertia_kgm2] * 6
        joint = [self.coulomb_Nm, self.viscous_Nms_rad, self.armature_kgm2, self.offset_Nm]
        return np.concatenate([np.tile(body, n), np.tile(joint, n)]).astype(float)


@dc.dataclass
class Robot:
    params: str = "builtin:kinova_gen3_params.yaml"  # joint parameters YAML (names the URDF)
    model: str = ""  # URDF/SDF; empty: the one named in `params`
    coulomb_smoothing_rad_s: float = 0.01  # Coulomb law Fc*tanh(v/vs); 0 = sign(v)
    # corrected_model.yaml of `safesysid diagnose`: its starting model with the diagnosed
    # friction/armature/offset is the robot model, its other effects fill plant.effects
    # (systems/model_corrections.py); robot.model and robot.params stay unset.
    corrected_model: str = ""


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
    # and the drawn real arm (ParameterFloors above has the defaults).
    theta_r_floor: ParameterFloors = dc.field(default_factory=ParameterFloors)


@dc.dataclass
class PlantEffects:
    """Effects the models above the plant do not know (all off by default)."""

    torque_sensor_offset_Nm: List[float] = dc.field(default_factory=list)
    torque_sensor_scale: List[float] = dc.field(default_factory=list)
    time_delay_s: float = 0.0
    torque_sensor_lag_s: float = 0.0  # first-order low-pass of the torque sensor signal
    torque_sensor_delay_s: float = 0.0  # the sensor reading arrives late (torque lags the motion)
    base_tilt_rad: List[float] = dc.field(default_factory=lambda: [0.0, 0.0])
    joint_stiffness_Nm_rad: List[float] = dc.field(default_factory=list)
    # Friction the robot model has no term for (the diagnosis' laws, sgn = the Coulomb shape):
    # load-dependent mu |tau_motor| sgn v [N m per N m of motor torque], per joint, in [0, 1) ...
    load_friction_mu: List[float] = dc.field(default_factory=list)
    # ... and Stribeck Fs sgn v exp(-(v / vs)^2): Fs per joint [N m], vs shared [rad/s].
    stribeck_friction_Nm: List[float] = dc.field(default_factory=list)
    stribeck_velocity_rad_s: float = 0.05


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
    """ARMOUR robust passivity controller (systems/armour.py) and the baselines."""

    Kr: List[float] = dc.field(default_factory=lambda: [5.0, 5.0, 5.0, 5.0, 7.0, 7.0, 7.0])
    alpha: float = 20.0
    # Lyapunov level of the tube [J]: the hardware value (eps = 0.072). With the Table II prior the
    # planner certifies the wrist torque through the affine tube enclosure (interval_dynamics.py):
    # 10/10 random starts plannable (0/10 with the interval boxes, which is why 0.005 was used).
    V_max: float = 0.02
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
    # Columns of W_e whose log cond the exciting cost minimises: all ten (the paper) or the six
    # rotational inertias only (the directions the paper's cost leaves poorly excited).
    exciting_columns: str = "all"  # all | inertia
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
    set_membership: str = "mass"  # LP refinement of [θ_e]: none | mass | all (estimation/enclosure.py)
    point_estimate: str = "map"  # θ0: map (θ_r marginalised) | paper (plain least squares)
    # Logged torque: held (zero-order hold, exact left sum) | continuous (trapezoid + rate bound).
    torque_signal: str = "held"
    hold_period_s: float = 0.0  # held: the hold period; 0 = plant.time_step_s
    torque_rate_limit_Nm_s: float = 200.0  # continuous: declared |dtau/dt|, checked on the data
    quadrature_safety: float = 2.0  # kappa of the quadrature bound (estimation/segments.py), >= 2


@dc.dataclass
class InitialInterval:
    """End-effector prior (paper Table II): nominal and box, theta order of systems/inertial.py NAMES."""

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


def resolve_path(text, base_dir):
    """`builtin:NAME` -> models/NAME; relative paths against the scenario's folder."""
    if text.startswith("builtin:"):
        return MODELS_DIR / text[len("builtin:") :]
    p = Path(text).expanduser()
    return p if p.is_absolute() else Path(base_dir) / p


def scenario_dir(s: Scenario):
    return Path(s.source).parent


def task_enabled(s: Scenario):
    """The scenario has a task phase (a goal or a platform)."""
    return bool(s.task.goal_q_rad or s.task.place_xyz_m or s.task.platform)


def robot_from_scenario(s: Scenario):
    """The RobotModel a scenario names (one source of truth for every system)."""
    from .robot_model import load_robot

    base = scenario_dir(s)
    if s.robot.corrected_model:
        from .model_corrections import CorrectionError, corrected_robot, load_starting_robot, read_correction

        try:
            corr = read_correction(resolve_path(s.robot.corrected_model, base))
            return corrected_robot(load_starting_robot(corr, s.robot.coulomb_smoothing_rad_s), corr)
        except CorrectionError as err:
            raise ScenarioError(f"{s.source}: robot.corrected_model: {err}") from err
    model = resolve_path(s.robot.model, base) if s.robot.model else None
    return load_robot(model, resolve_path(s.robot.params, base), coulomb_smoothing=s.robot.coulomb_smoothing_rad_s)
