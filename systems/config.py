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

import numpy as np

from .methods import FOURIER, METHODS_SPEC, MethodSpec

List = list
Optional = typing.Optional

MAX_CONTROL_STEP_S = 0.001


METHODS = tuple(METHODS_SPEC)  # the paper's table of comparisons, in its order


def one_of(*allowed: str, default: str | None = None) -> str:
    """A string field that takes one of `allowed` (default: the first), listed in its metadata
    "choices": the loader checks it (app/scenario.py), the scenario reference lists it."""
    value = allowed[0] if default is None else default
    assert value in allowed, (value, allowed)
    return dc.field(default=value, metadata={"choices": allowed})


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

    def per_parameter(self, n: int) -> np.ndarray:
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
    # (systems/model/corrections.py); robot.model and robot.params stay unset.
    corrected_model: str = ""


@dc.dataclass
class BoundingVolume:
    """A region known to contain the payload (not the gripper), in the end-effector frame: an
    ellipsoid (half_extent_m = semi-axes) or a box (half side lengths), centre_m and rpy_rad of its
    axes. Used by estimator.physical_pruning (systems/estimation/physical.py)."""

    shape: str = one_of("none", "ellipsoid", "box")
    centre_m: List[float] = dc.field(default_factory=lambda: [0.0, 0.0, 0.0])
    half_extent_m: List[float] = dc.field(default_factory=lambda: [0.0, 0.0, 0.0])
    rpy_rad: List[float] = dc.field(default_factory=lambda: [0.0, 0.0, 0.0])


@dc.dataclass
class Payload:
    dumbbell: str = "4lb"  # key of models/dumbbells.yaml, or "none"
    dumbbells_file: str = "builtin:dumbbells.yaml"
    bounding_volume: BoundingVolume = dc.field(default_factory=BoundingVolume)


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
    distribution: str = one_of("uniform", "none")  # uniform: inside the declared bound
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
    # quasi_static: the link moves as if rigid and motor-side encoders read q + tau / K (tau of the
    # last plant step);
    # dynamic: a motor (inertia = the armature) drives each link through the spring and a damper
    # (joint_damping_Nms_rad), the encoders read the link; systems/plant/stages.py ElasticTransmission.
    joint_elasticity: str = "quasi_static"
    joint_damping_Nms_rad: List[float] = dc.field(default_factory=list)
    # Friction the robot model has no term for (the diagnosis' laws, sgn = the Coulomb shape):
    # load-dependent mu |tau_motor| sgn v [N m per N m of motor torque], per joint, in [0, 1) ...
    load_friction_mu: List[float] = dc.field(default_factory=list)
    # ... and Stribeck Fs sgn v exp(-(v / vs)^2): Fs per joint [N m], vs shared [rad/s].
    stribeck_friction_Nm: List[float] = dc.field(default_factory=list)
    stribeck_velocity_rad_s: float = 0.05
    # Encoder velocity noise: uniform in +-bound on each joint's measured velocity, every step
    # (controller and estimator read it; the referee judges the plant's true state).
    velocity_noise_rad_s: float = 0.0


@dc.dataclass
class Plant:
    time_step_s: float = 0.001
    # The real arm's robot parameters (links, friction, armature, offsets): the model's nominal
    # values, drawn uniformly inside the declared box (seeded; links kept physically consistent),
    # or at a random vertex of it (pulled inside where a vertex is not physically consistent).
    robot_parameters: str = one_of("nominal", "drawn", "corner")
    effects: PlantEffects = dc.field(default_factory=PlantEffects)


@dc.dataclass
class Controller:
    """ARMOUR robust passivity controller (systems/controller/armour.py) and the baselines."""

    # Per-joint lists left empty here are the robot's: its parameter file's `defaults:` or a rule
    # (systems/model/robot_defaults.py, docs/own-robot.md "Defaults"), filled when loaded.
    Kr: List[float] = dc.field(default_factory=list)
    alpha: float = 20.0
    # Lyapunov level of the tube [J]: the hardware value (eps = 0.072). With the Table II prior the
    # planner certifies the wrist torque through the affine tube enclosure (interval_dynamics.py):
    # 10/10 random starts plannable (0/10 with the interval boxes, which is why 0.005 was used).
    V_max: float = 0.02
    # closed_loop.build_closed_loop's controller; an online run's controllers are its method's
    # (systems/methods.py).
    kind: str = one_of("armour", "pid", "adaptive", "adaptive_robust")
    # Baselines (systems/controller/systems.py), per joint; empty: the robot's (Kp ~ M (10 rad/s)^2,
    # Kd ~ 2 M 10 rad/s by the rule, M the joint's largest inertia).
    pid_kp_Nm_rad: List[float] = dc.field(default_factory=list)
    pid_ki_Nm_rad_s: List[float] = dc.field(default_factory=list)
    pid_kd_Nms_rad: List[float] = dc.field(default_factory=list)
    adaptive_kd_Nms_rad: List[float] = dc.field(default_factory=list)
    # Adaptation gain per end-effector parameter [m, m c (3), I (6)] (units of theta_e^2 / (N m rad)).
    adaptive_gamma: List[float] = dc.field(default_factory=lambda: [5.0, 1.0, 1.0, 1.0, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1])
    adaptive_boundary_rad_s: float = 0.05  # boundary layer of the adaptive robust (adap-2) term


@dc.dataclass
class Planner:
    duration_s: float = 3.0  # t_f
    replan_period_s: float = 1.5  # t_p
    num_plans: int = 4
    # End positions q0 + k_center + k_range * k, k in [-1, 1]; empty: the robot's.
    k_center_rad: List[float] = dc.field(default_factory=list)
    k_range_rad: List[float] = dc.field(default_factory=list)
    num_time_intervals: int = 128  # reachability over-approximation
    num_cost_samples: int = 128  # N_s of the exciting cost
    cost: str = one_of("exciting", "goal", "random")
    # Columns of W_e whose log cond the exciting cost minimises: all ten (the paper) or the six
    # rotational inertias only (the directions the paper's cost leaves poorly excited).
    exciting_columns: str = one_of("all", "inertia")
    # What the exciting cost minimises: cond, the paper's log cond(W_e); a_optimal, log of the sum
    # over parameters of the least-squares variance the plan would leave, each relative to its
    # current interval width squared (the widths the estimator publishes, not the ratio of extremes);
    # e_optimal, -log sigma_min, and cond_interval, log cond, of W_e with each column times its
    # parameter's current interval width; d_optimal, -1/2 log det W_e^T W_e, the classic D-optimal
    # design, blind to column scales (README "Tried and no better": all four narrow less than cond).
    exciting_criterion: str = one_of("cond", "a_optimal", "e_optimal", "cond_interval", "d_optimal")
    # Rows of W_e the exciting cost sees: none, as they are (the paper); noise, each divided by
    # the declared torque-noise bound of its joint and instant (noise.declared_*, on the nominal
    # torque of the plan that keeps k = 0), the scale of the rows the estimator's intervals are
    # made of: a direction seen only on a noisy joint (joint 2's gravity load, joint 7's
    # armature) counts for what it is worth there.
    exciting_weighting: str = one_of("none", "noise")
    # true (default): the exciting cost conditions the motion executed so far stacked with the
    # candidate plan, so each plan excites what the data still lack (cond(Y) well below random
    # plans'); false: the plan alone, the paper's cost, whose data are no better conditioned than
    # random plans' at the hardware V_max 0.02 (docs/identification.md).
    cumulative_excitation: bool = True
    # true: a plan certified on its own k (each plan only needs its own k safe; a box is certified
    # for every k in it, so it shrinks much more), the certified k box only when no such point is
    # found: SafePlanner._refine. Larger motions, the same checks. false: the box alone.
    point_refinement: bool = False
    # The fraction of the position/velocity limit box (around k = 0) that refinement's wide solve
    # searches: its optimum is then scaled toward k = 0 until certified, so an optimum found among
    # motions of about the certifiable size keeps more of its excitation than a scaled-down larger one.
    refinement_scale: float = 1.0
    # true: refinement adopts a point only if the state its plan reaches at the next call (t_p) has
    # a certified plan k = 0 (with k_center 0 it holds still there; halving the point toward k = 0,
    # up to 3 times), and a point's last shrink level is k = 0 itself: a most exciting plan no longer
    # leaves the arm where nothing can be certified and it must brake. Needs point_refinement.
    continuation: bool = False
    goal_q_rad: List[float] = dc.field(default_factory=list)
    solver: str = one_of("ipopt", "snopt")
    max_solve_time_s: float = 1.2  # wall cap inside t_p (budget: wall_time only)
    max_iterations: int = 100
    # What stops a planning call's solver. iterations: max_iterations alone, so the same scenario
    # and seed give the same plans (and summary.json) under any machine load; the default, used
    # by run, compare, sweep and the tests. wall_time: also max_solve_time_s, the real-time mode
    # (the deadline benchmark): which iterate is kept then depends on the machine's speed and load.
    budget: str = one_of("iterations", "wall_time")
    floor_z_m: float = 0.0  # floor plane height (an obstacle)


@dc.dataclass
class FourierExcitation:
    """The classical exciting trajectory of method grav-pid-excit (systems/excitation/fourier.py):
    one period of a finite Fourier series from rest at q0 back to rest at q0, optimized for
    cond(W_e) inside the joint velocity limits (robot params) and these acceleration limits only."""

    period_s: float = 7.5  # as long as the planner's identification phase, (4 - 1) 1.5 s + 3 s
    num_harmonics: int = 5
    # Per joint; empty: the robot's (the Gen3's: its RAPTOR constants; a rule from the velocity limits).
    acceleration_limit_rad_s2: List[float] = dc.field(default_factory=list)
    num_cost_samples: int = 64
    max_iterations: int = 60


@dc.dataclass
class Estimator:
    horizon_s: float = 0.1  # segment length h
    integration: str = one_of("trapezoid", "euler")  # euler: the paper's
    solver: str = one_of("ipopt", "snopt")
    max_gap_s: float = 0.05  # a segment never spans a time step longer than this
    # LP refinement of [θ_e] (estimation/enclosure.py) of nothing, the mass or all; all, the default, bounds
    # each of the ten parameters as the paper's Fig. 5 does (~2x the update's CPU: docs/identification.md)
    set_membership: str = one_of("none", "mass", "all", default="all")
    # > 0: that LP on the segments of the last this many seconds only, inside the interval the
    # older ones gave (an update's cost stops growing with the run); 0: on every segment.
    set_membership_window_s: float = 0.0
    point_estimate: str = one_of("map", "paper")  # θ0: map (θ_r marginalised), paper (plain least squares)
    # Logged torque: held (zero-order hold, exact left sum), continuous (trapezoid + rate bound).
    torque_signal: str = one_of("held", "continuous")
    hold_period_s: float = 0.0  # held: the hold period; 0 = plant.time_step_s
    torque_rate_limit_Nm_s: float = 200.0  # continuous: declared |dtau/dt|, checked on the data
    # held: the torque sensor's first-order lag (time constant; 0 = none), undone exactly
    # (estimation/lag.py), or [lo, hi]: some lag in it, enclosed over the interval (the list
    # first: yaml_load_typed rejects a list for `float | list[float]`); set with
    # plant.effects.torque_sensor_lag_s by robot.corrected_model (its interval when it has one).
    torque_lag_s: list[float] | float = 0.0
    # held: the logged torque of step k is the sample this much later (> 0: a late reading, < 0: a
    # late torque), re-paired exactly (estimation/delay.py); robot.corrected_model sets it with the
    # plant's torque_sensor_delay_s / time_delay_s.
    torque_delay_s: float = 0.0
    quadrature_safety: float = 2.0  # kappa of the quadrature bound (estimation/segments.py), >= 2
    # |q̈_j| between the samples never exceeds it (rad/s², one value or one per joint; empty: not
    # declared): each step's quadrature term is then certified without A5, A5 checked against it,
    # and samples that contradict it latch consistent off (estimation/quadrature_certificate.py).
    acceleration_bound_rad_s2: list[float] = dc.field(default_factory=list)
    # Derive |q̈_j| between the samples per step instead, from the model's dynamics under the held
    # torque and the estimator's own parameter box (estimation/acceleration_bound.py); needs
    # torque_signal held and no acceleration_bound_rad_s2.
    derive_acceleration_bound: bool = False
    # Prune the published box with physical knowledge: J(theta_e) >= 0 and, with a
    # payload.bounding_volume, its density-realizability LMI (estimation/physical.py).
    physical_pruning: bool = False


@dc.dataclass
class InitialInterval:
    """End-effector prior: nominal and box, theta order of systems/model/inertial.py NAMES. Empty:
    the prior the robot's parameter file declares (the Gen3's: the paper's Table II)."""

    nominal: List[float] = dc.field(default_factory=list)
    lower: List[float] = dc.field(default_factory=list)
    upper: List[float] = dc.field(default_factory=list)
    # A robot without a declared prior: with payload_mass_kg [lo, hi] set, nominal/lower/upper are
    # derived at load from the end-effector body plus any payload of such mass lying in the box of
    # payload_half_extent_m about payload_centre_m (end-effector frame and axes; empty centre: the
    # robot's grasp point), systems/estimation/prior.py; the three lists must then not be given.
    payload_mass_kg: List[float] = dc.field(default_factory=list)
    payload_centre_m: List[float] = dc.field(default_factory=list)
    payload_half_extent_m: List[float] = dc.field(default_factory=lambda: [0.0, 0.0, 0.0])


@dc.dataclass
class Task:
    """Task phase (paper §VII): after identification the arm follows a trajectory computed
    offline (systems/task/trajectory.py) from q0_rad to a goal, then releases the payload.

    Goal: `goal_q_rad` (a joint configuration) or a placement: the payload (dumbbell) centre at
    `place_xyz_m`, handle horizontal, gripper vertical (Drake InverseKinematics, then free in the
    optimization); with neither, the centre goes above the top centre of the obstacle named
    `platform` so that its lowest point is `release_height_m` above it. No goal, no platform:
    no task phase.

    In `safesysid run` (app/online.py): after the identification phase (at once for methods
    without one) the arm returns to q0_rad by a verified minimum-jerk move of `return_duration_s`
    if identification left it elsewhere, follows the (cached) task trajectory, releases the
    payload at its end and waits `settle_time_s` for it to come to rest.

    Success (summary.json `success`; the first failure and its `phase` otherwise): no contact of
    the link shapes or payload with the environment (min clearance > 0 m, the referee's Drake
    geometry), commanded torque <= limit BEFORE saturation, joints and velocities within their
    limits, tracking error <= the controller's certified tube bound (rad, per joint), and, with a
    placement, the settled payload centre within `placement_tolerance_m` of its target (resting on
    the platform under the release point: platform top + the payload's resting radius; with
    `place_xyz_m` and no platform, the centre at release vs `place_xyz_m`).
    """

    goal_q_rad: List[float] = dc.field(default_factory=list)
    place_xyz_m: List[float] = dc.field(default_factory=list)  # payload centre target, base frame
    platform: str = ""  # name of the obstacle (in `obstacles`) the payload is placed on
    # Stacking (paper §VII): dumbbells already placed on the platform, bottom first; each becomes a
    # box on the stack (task_phase.stack_boxes) and the payload is placed on the top one.
    stack_on: List[str] = dc.field(default_factory=list)
    release_height_m: float = 0.03  # payload's lowest point above the platform top at release
    placement_tolerance_m: float = 0.01  # success: |settled payload centre - target| (see above)
    return_duration_s: float = 2.0  # identification end -> q0_rad (one degree-5 piece)
    settle_time_s: float = 1.0  # simulated after the release before the placement is measured
    cache_dir: str = ""  # task-trajectory cache; empty: $XDG_CACHE_HOME (or ~/.cache)/safesysid/task
    duration_s: float = 2.0  # paper: 2 s
    num_pieces: int = 2  # degree-5 Bézier pieces of equal length, C2 at the junctions
    payload_model: str = "8lb"  # dumbbell whose model the trajectory is computed with
    collision_samples: int = 200  # sphere/obstacle checks (+ a margin for the motion in between)
    torque_samples: int = 41  # inverse-dynamics checks
    torque_margin_ratio: float = 0.2  # nominal torque <= (1 - ratio) * limit (room for the tube)
    solver: str = one_of("snopt", "ipopt")  # snopt: Ipopt as its fallback
    max_iterations: int = 500
    max_solve_time_s: float = 120.0  # wall-time cap per solver (offline; the result is cached)
    # Certificate (app/task_run.py): ARMOUR's torque bound over the tube and the box latched at the
    # switch must be <= 1; else the same path is played slower, at the smallest scale on the grid
    # 1, 1 + step, ... up to max_time_scale (x the planned duration, dimensionless) that certifies;
    # none: the task is refused (failure task_uncertified, the arm holds).
    max_time_scale: float = 3.0  # slowest play allowed, x the planned duration (1: never slower)
    time_scale_step: float = 0.25  # step of the grid of scales tried (x the planned duration)


@dc.dataclass
class ScheduledObstacle(Obstacle):
    """An obstacle that appears at t_s (systems/plant/faults.py): the planner learns of it then; the
    referee's world holds it from the start (stricter: a contact at any time counts)."""

    name: str = "appearing"
    t_s: float = 1.0


@dc.dataclass
class Faults:
    """Injected faults (systems/plant/faults.py; all off by default), each logged in summary.json events.
    Random faults draw from the run's seeded noise (Drake RandomSource), a rate r per second
    firing at a step with probability r * plant.time_step_s."""

    # Torque sensor: spikes of +-magnitude on one random joint (of `torque_spike_joints`, 1-based;
    # empty: all) at a rate; a dropout (the sensor reads 0 N m) over [start, start + duration).
    torque_spike_magnitude_Nm: float = 0.0
    torque_spike_rate_per_s: float = 0.0
    torque_spike_joints: List[int] = dc.field(default_factory=list)
    torque_dropout_start_s: float = 0.0
    torque_dropout_duration_s: float = 0.0
    # Samples reaching the estimator: lost, delivered twice, delivered one step late (after the
    # next one), or with a NaN in one field.
    sample_drop_rate_per_s: float = 0.0
    sample_duplicate_rate_per_s: float = 0.0
    sample_reorder_rate_per_s: float = 0.0
    sample_nan_rate_per_s: float = 0.0
    # Planner: the planning calls (0-based) whose solver fails or times out (no verified plan).
    planner_failure_calls: List[int] = dc.field(default_factory=list)
    planner_failure_kind: str = one_of("solver_failed", "timeout")
    appearing_obstacles: List[ScheduledObstacle] = dc.field(default_factory=list)
    # The real payload is heavier than the scenario's dumbbell by this much (same shape, denser).
    payload_extra_mass_kg: float = 0.0
    # Joint-velocity sensor reading clipped to +-limit (encoders' v, seen by controller and estimator).
    velocity_clip_rad_s: float = 0.0  # 0: off

    def samples_faulty(self) -> bool:
        return any(
            r > 0
            for r in (
                self.sample_drop_rate_per_s,
                self.sample_duplicate_rate_per_s,
                self.sample_reorder_rate_per_s,
                self.sample_nan_rate_per_s,
            )
        )


@dc.dataclass
class Arm:
    """Which arm the run drives (docs/hardware.md): the simulated station in this process, or an
    arm reached over LCM (Drake's lcmt_panda_command / lcmt_panda_status, torque mode), answered by
    `safesysid arm-sim` or a hardware driver."""

    driver: str = one_of("simulated", "lcm")
    lcm_url: str = "udpm://239.241.129.92:20185?ttl=0"  # ttl=0: this machine only
    command_channel: str = "SAFESYSID_ARM_COMMAND"
    status_channel: str = "SAFESYSID_ARM_STATUS"
    watchdog_ms: float = 20.0  # the driver brakes when no new command arrived for this long
    status_timeout_ms: float = 20.0  # the run brakes when no new status arrived for this long
    # The payload's release (lcmt_schunk_wsg_command / _status, systems/hardware/gripper.py).
    gripper_command_channel: str = "SAFESYSID_GRIPPER_COMMAND"
    gripper_status_channel: str = "SAFESYSID_GRIPPER_STATUS"
    gripper_timeout_ms: float = 500.0  # no "open" status this long after asking: the run holds the arm
    # Where the 1 kHz robust controller runs: beside the arm (`arm-sim` runs it; each certified
    # plan crosses once on plan_channel) or in the run (torques cross at 1 kHz on command_channel:
    # an arm driver that takes torques, e.g. drake-franka-driver).
    control_loop: str = one_of("arm", "run")
    plan_channel: str = "SAFESYSID_ARM_PLAN"  # run -> arm, control_loop arm: lcmt_drake_signal plans
    # control_loop arm: the run's clock starts this far ahead on the arm's (the first plan's transit)
    plan_lead_ms: float = 200.0
    # control_loop arm: the run's loop period (no controller in it: it hands the statuses received
    # to the estimator and plans); a multiple of plant.time_step_s dividing planner.replan_period_s
    run_step_ms: float = 10.0


@dc.dataclass
class Scenario:
    name: str = "scenario"
    robot: Robot = dc.field(default_factory=Robot)
    q0_rad: List[float] = dc.field(default_factory=list)  # start pose; empty: the robot's
    payload: Payload = dc.field(default_factory=Payload)
    obstacles: List[Obstacle] = dc.field(default_factory=list)
    noise: Noise = dc.field(default_factory=Noise)
    plant: Plant = dc.field(default_factory=Plant)
    controller: Controller = dc.field(default_factory=Controller)
    planner: Planner = dc.field(default_factory=Planner)
    fourier: FourierExcitation = dc.field(default_factory=FourierExcitation)
    estimator: Estimator = dc.field(default_factory=Estimator)
    initial_interval: InitialInterval = dc.field(default_factory=InitialInterval)
    task: Task = dc.field(default_factory=Task)
    faults: Faults = dc.field(default_factory=Faults)
    arm: Arm = dc.field(default_factory=Arm)
    method: str = one_of(*METHODS, default="ours")  # systems/methods.py: the paper's table of comparisons
    seed: int = 0
    # Where the loader found the file (not a YAML field).
    source: str = ""


def task_enabled(s: Scenario) -> bool:
    """The scenario has a task phase (a goal or a platform)."""
    return bool(s.task.goal_q_rad or s.task.place_xyz_m or s.task.platform)


def excitation_duration_s(spec: MethodSpec, scenario: Scenario) -> float:
    """Length of the identification phase: planner (N - 1) t_p + t_f, Fourier one period, else 0."""
    if spec.excitation is None:
        return 0.0
    if spec.excitation.trajectory == FOURIER:
        return float(scenario.fourier.period_s)
    return planner_horizon_s(scenario)


def loop_step_s(s: Scenario) -> float:
    """The run's loop period [s]: the plant step, or arm.run_step_ms with the controller beside an
    arm reached over LCM (arm.control_loop arm)."""
    if s.arm.driver == "lcm" and s.arm.control_loop == "arm":
        return s.arm.run_step_ms * 1e-3
    return s.plant.time_step_s


def planner_horizon_s(scenario: Scenario) -> float:
    """Algorithm 2's identification phase: plans start every t_p, the last runs t_f to rest."""
    p = scenario.planner
    return (p.num_plans - 1) * p.replan_period_s + p.duration_s
