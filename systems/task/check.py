"""Checks of a task trajectory (systems/task/trajectory.py) that do not trust the optimizer: the
independent verification on the referee's geometry and Drake's dynamics, and the ARMOUR
controller's certified torque bound over the tube and a parameter box."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from safesysid.systems.math.bezier import _difference, restriction_matrix
from safesysid.systems.math.piecewise_bezier import DEGREE, PiecewiseBezier
from safesysid.systems.planner import interval_dynamics as idyn
from safesysid.systems.planner import torque_certificate as tcert
from safesysid.systems.task.constraints import GRIPPER_TILT_TOL_RAD, PLACEMENT_TOL_M
from safesysid.systems.task.problem import TaskProblem, jsonable


def certified_torque_ratio(
    problem: TaskProblem,
    trajectory: PiecewiseBezier,
    theta0: np.ndarray,
    theta_lo: np.ndarray,
    theta_hi: np.ndarray,
    *,
    windows_per_piece: int = 100,
) -> tuple[float, np.ndarray]:
    """max_j sup |u_j| / limit_j of the ARMOUR command while tracking `trajectory`: over every
    instant (windows tiling each piece, Bézier hulls of q, dq, ddq), every tracking error in the
    tube and every theta in [theta_lo, theta_hi] (reachability's interval passivity regressor and
    robust-term bound, as the planner certifies its plans). <= 1: the controller's certificate
    covers the task trajectory with that parameter box. Returns (ratio, per-joint sup |u| (n,))."""
    from safesysid.systems.math.intervals import Interval, _down, _up

    tb = problem.tracking
    edges = np.linspace(0.0, 1.0, windows_per_piece + 1)
    hulls = []
    for order in range(3):
        lo, hi = [], []
        for pts in trajectory.control_points:
            d = _difference(pts, order) / trajectory.piece_duration**order
            sub = np.stack([restriction_matrix(DEGREE - order, a, b) @ d for a, b in zip(edges[:-1], edges[1:])])
            lo.append(sub.min(1))
            hi.append(sub.max(1))
        hulls.append((np.concatenate(lo), np.concatenate(hi)))
    (q_lo, q_hi), (v_lo, v_hi), (a_lo, a_hi) = hulls

    def pad(lo, hi, r):  # outward, as reachability.PlanReach.state_boxes
        return Interval(_down(_down(lo - r) - 1e-12 * np.abs(lo)), _up(_up(hi + r) + 1e-12 * np.abs(hi)))

    q_box = pad(q_lo, q_hi, tb.position)
    wp = idyn.interval_passivity_regressor(
        problem.robot, q_box, pad(v_lo, v_hi, tb.velocity), pad(v_lo, v_hi, tb.qd_a), pad(a_lo, a_hi, tb.qdd_a)
    )
    # The robust input may exceed |w_bar| on the tube (h < 0): the same excess the planner adds.
    excess = tcert.barrier_excess(problem.robot, q_box, theta_lo, theta_hi, tb)
    sup, _, _ = tcert.torque_bound(wp, theta0, theta_lo, theta_hi=theta_hi, excess=excess)
    per_joint = sup.max(0)
    return float(np.max(per_joint / problem.robot.joint_params.torque_limit)), per_joint


def time_scaled(trajectory: PiecewiseBezier, scale: float) -> PiecewiseBezier:
    """The same path `scale` times slower: the same control points over pieces `scale` times
    longer (velocity / scale, acceleration / scale^2; still at rest at both ends)."""
    return PiecewiseBezier(trajectory.control_points, trajectory.piece_duration * float(scale))


def time_scale_grid(max_scale: float, step: float) -> list[float]:
    """1, 1 + step, 1 + 2 step, ... up to max_scale, max_scale itself always last."""
    count = int(np.floor((max_scale - 1.0) / step + 1e-9))
    grid = [1.0 + k * step for k in range(count + 1)]
    return grid + ([float(max_scale)] if max_scale - grid[-1] > 1e-9 else [])


@dataclass
class ScaledCertificate:
    """The smallest time scale on a grid whose certificate is <= 1 (None: none up to the cap)."""

    time_scale: float | None
    ratio: float  # the certificate at time_scale, or at the last scale tried when refused
    tried: list  # [(scale, certificate)] in the order tried

    @property
    def certified(self) -> bool:
        return self.time_scale is not None


def smallest_certified_scale(certificate: Callable[[float], float], scales: Sequence[float]) -> ScaledCertificate:
    """Try `scales` in increasing order and stop at the first whose certificate(scale) <= 1. Each
    scale is certified on its own, so nothing rests on the certificate decreasing with the scale
    (it need not: the tube's velocity and acceleration pads do not shrink); the scale returned is
    the smallest on the grid, not the smallest real number that certifies."""
    tried = []
    for scale in sorted(scales):
        ratio = float(certificate(scale))
        tried.append((float(scale), ratio))
        if ratio <= 1.0:
            return ScaledCertificate(float(scale), ratio, tried)
    return ScaledCertificate(None, tried[-1][1], tried)


def phase_certificate(
    problem: TaskProblem, curves: Sequence[PiecewiseBezier], thetas: Sequence[np.ndarray], *, scale: float
) -> float:
    """certified_torque_ratio of every curve of the task phase played `scale` times slower, with
    the parameter box (theta0, lower, upper): the largest."""
    theta0, lo, hi = (np.asarray(x, float) for x in thetas)
    return max(certified_torque_ratio(problem, time_scaled(c, scale), theta0, lo, hi)[0] for c in curves)


# ---------------------------------------------------------------------------------------------
# Independent verification (the referee's geometry and Drake's dynamics)
# ---------------------------------------------------------------------------------------------
@dataclass
class TaskVerification:
    ok: bool  # no contact with obstacles/floor, limits respected with the stated margins
    min_clearance_m: float  # Drake signed distance, link shapes + payload vs obstacles + floor
    closest_pair: tuple
    max_torque_ratio: float  # max |tau_j| / limit_j, Drake inverse dynamics + joint friction
    max_velocity_ratio: float  # max |v_j| / limit_j
    max_joint_limit_ratio: float  # safety_monitor.limit_ratio (1 = at a limit)
    placement_error_m: float  # |payload centre at the end - target| (nan for a joint goal)
    gripper_tilt_rad: float  # angle of the gripper axis from vertical at the end
    num_samples: int
    failures: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return jsonable(self.__dict__)


def verify_task_trajectory(
    problem: TaskProblem, trajectory: PiecewiseBezier, rate_hz: float = 1000.0
) -> TaskVerification:
    """Re-check a trajectory at `rate_hz` with what the closed-loop referee uses: the real arm's
    scene (systems/plant/station.py: link shapes, the payload's cylinders, obstacles, floor) queried
    by SafetyMonitor.min_clearance, and Drake's CalcInverseDynamics on that plant (rotor inertia
    = armature, the payload model) plus the plant's joint friction law. Nothing here uses the
    planner spheres or the regressors. Pass/fail against the margins the optimizer claims: no
    contact; velocity <= limit - tube velocity bound; position within limits - tube position
    bound; torque <= limit (the margin ratio is claimed at the optimizer's torque samples only,
    so the dense check asks for the limit itself and reports the ratio)."""
    from pydrake.multibody.tree import MultibodyForces
    from pydrake.systems.framework import DiagramBuilder
    from safesysid.systems.config import Planner, Scenario
    from safesysid.systems.model.regressors import coulomb_shape
    from safesysid.systems.plant.safety_monitor import SafetyMonitor, limit_ratio
    from safesysid.systems.plant.station import add_real_arm

    robot = problem.robot
    jp = robot.joint_params
    tb = problem.tracking
    builder = DiagramBuilder()
    scene = Scenario(
        obstacles=list(problem.obstacles),
        planner=Planner(floor_z_m=problem.floor_z if problem.floor_z is not None else -100.0),
    )
    arm = add_real_arm(builder, scene, robot=robot, dumbbell=problem.dumbbell)
    monitor = builder.AddSystem(SafetyMonitor(arm.plant, arm.scene_graph, robot, period_s=1.0))
    diagram = builder.Build()
    root = diagram.CreateDefaultContext()
    plant = arm.plant
    pctx = plant.GetMyMutableContextFromRoot(root)
    sg_ctx = arm.scene_graph.GetMyContextFromRoot(root)
    t = np.linspace(0.0, trajectory.duration, int(round(trajectory.duration * rate_hz)) + 1)
    q, v, a = trajectory.evaluate(t, orders=2)
    clearance, pair, tau = np.inf, None, np.zeros_like(q)
    forces = MultibodyForces(plant)
    friction = lambda vel: jp.coulomb * coulomb_shape(vel, robot.coulomb_smoothing) + jp.viscous * vel + jp.offset  # noqa: E731
    for k in range(len(t)):
        plant.SetPositions(pctx, arm.instance, q[k])
        plant.SetVelocities(pctx, arm.instance, v[k])
        d, p = monitor.min_clearance(arm.scene_graph.get_query_output_port().Eval(sg_ctx))
        if d < clearance:
            clearance, pair = d, p
        plant.CalcForceElementsContribution(pctx, forces)
        tau[k] = plant.CalcInverseDynamics(pctx, a[k], forces) + friction(v[k])
    torque_ratio = float(np.max(np.abs(tau) / jp.torque_limit))
    vel_ratio = float(np.max(np.abs(v) / jp.velocity_limit))
    joint_ratio = float(np.max(limit_ratio(q, jp.position_lower, jp.position_upper)))
    ee = plant.GetBodyByName(robot.body_names[robot.end_effector]).body_frame()
    plant.SetPositions(pctx, arm.instance, q[-1])
    pose = plant.CalcRelativeTransform(pctx, plant.world_frame(), ee)
    tilt = float(np.arccos(np.clip(pose.rotation().matrix()[2, 2], -1.0, 1.0)))
    place_err = float("nan")
    if problem.place_xyz is not None:
        place_err = float(np.linalg.norm(pose @ np.asarray(robot.extra["grasp_point"], float) - problem.place_xyz))
    failures = []
    if clearance <= 0:
        failures.append(f"contact: clearance {clearance:.4f} m ({pair})")
    if np.any(np.abs(v) > jp.velocity_limit - tb.velocity + 1e-9):
        failures.append("velocity above limit - tube bound")
    if np.any(q < jp.position_lower + tb.position - 1e-9) or np.any(q > jp.position_upper - tb.position + 1e-9):
        failures.append("position outside limits - tube bound")
    if torque_ratio > 1:
        failures.append(f"torque ratio {torque_ratio:.3f} > 1")
    if (
        np.max(np.abs(v[[0, -1]])) > 1e-9
        or np.max(np.abs(a[[0, -1]])) > 1e-9
        or np.max(np.abs(q[0] - problem.q_start)) > 1e-9
    ):
        failures.append("does not start at q_start at rest or does not end at rest")
    if problem.place_xyz is not None and (
        place_err > PLACEMENT_TOL_M * np.sqrt(3) + 1e-9 or tilt > GRIPPER_TILT_TOL_RAD
    ):
        failures.append(f"placement error {place_err:.4g} m, gripper tilt {tilt:.3g} rad")
    if problem.goal_q is not None and np.max(np.abs(q[-1] - problem.goal_q)) > 1e-6:
        failures.append("does not end at goal_q")
    return TaskVerification(
        not failures, float(clearance), pair, torque_ratio, vel_ratio, joint_ratio, place_err, tilt, len(t), failures
    )
