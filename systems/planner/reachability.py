"""Rigorous per-time-interval over-approximations of what the arm can reach while tracking a plan.

Pure math for the planner (systems/planner/safe_planner.py). A plan is the quintic Bézier of systems/math/bezier.py
from the current (q0, qd0, qdd0) to q_end = q0 + k_c + k_r * k, k in [-1, 1]^n, tracked by the
robust passivity controller whose ultimate bound gives controller.TrackingBounds. [0, t_f] is
split into intervals I_i; every statement holds for EVERY t in I_i (continuous time), every
tracking error inside the bound and every theta in [theta]:

1. Joint boxes. On I_i, q_d(t; k) - q_d(t_mid; k) = a(t) + (w(t) - w(t_mid)) k_r k, with a(t) the
   k = 0 deviation and w the (scalar) end weight of the Bézier. Both are Bézier curves; restricted
   to I_i their control points contain them (hull property), so |q_d(t; k) - q_d(t_mid; k)| <=
   dev_i := max|restricted a| + max|restricted w - w(t_mid)| k_r, for all k. With the tracking
   error |q - q_d| <= e_q: q(t) in q_mid_i(k) +- rho_i, rho_i = dev_i + e_q, a k-independent radius
   around a centre affine in k.
2. Joint position/velocity limits. The restricted control points of q_d (and of qd_d) on every I_i
   are affine in q_end_j alone; requiring each inside the limits shrunk by the tracking bound is a
   set of 1-d linear inequalities in k_j, i.e. a box in k (exact hull property, no sampling).
3. Collision. Sphere centre c_s(q) has |dc_s/dq_j| = |z_j x (c_s - o_j)| (distance to axis j);
   globally <= L_sj, the length of the fixed chain from joint j's axis to the centre (triangle
   inequality along the links), and on a box around q_c <= its value at q_c plus the drift that
   joints below j can cause (`local_spread`). By the mean value theorem along the segment inside
   the joint box, |c_s(q) - c_s(q_mid)| <= sum_j L~_sj rho_ij =: spread_is. The constraint
   sd(c_s(q_mid_i(k)), obstacle) >= r_s + spread_is keeps the whole sphere out of the obstacle on
   I_i (sd is 1-Lipschitz); it is C1 in k outside the obstacle. The planner hands the solver a
   soft-min per (sphere, obstacle) over the intervals, which is <= the true min, and verifies
   every pair exactly.
4. Torque (systems/planner/interval_dynamics.py). The commanded input is u = W_p(q, qd, qd_a, qdd_a) theta0 + v
   with |v_j| <= lambda <=
   ||w_bar||_2 + (alpha/2) eps mu(q) on the tube (controller.robust_gain_bound: lambda exceeds
   ||w_bar|| where h < 0, which happens inside the tube; mu bounds the spread of M over [theta],
   `interval_mass_spread` over the interval's configuration box) and
   w_bar_i <= sum_k |W_p,ik| max(theta_hi - theta0, theta0 - theta_lo)_k (the controller's
   interval disturbance bound). An interval evaluation of the passivity regressor
   (interval RNEA in local frames, outward rounded) over the state box of I_i that covers every
   k of the allowed box and the tracking tube bounds sup|u_j| rigorously; the planner requires
   it to be inside the torque limit for every interval (a check over the whole k box, on hulls of
   adjacent intervals; if it fails the k box is shrunk toward k = 0).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.controller.armour import (
    TrackingBounds,  # the controller's certified bounds (position, velocity, qd_a, qdd_a)
)
from safesysid.systems.math.bezier import QuinticBezier, restriction_matrix
from safesysid.systems.math.intervals import Interval, _down, _up
from safesysid.systems.model import regressors
from safesysid.systems.model.robot_model import carrier_index
from safesysid.systems.planner.interval_dynamics import merge_rows

if TYPE_CHECKING:
    from safesysid.systems.config import Obstacle
    from safesysid.systems.model.payload import Dumbbell
    from safesysid.systems.model.robot_model import JointParameters, RobotModel
    from safesysid.systems.planner.affine_forms import Affine

# ---------------------------------------------------------------------------------------------
# Collision geometry: spheres on bodies, oriented boxes
# ---------------------------------------------------------------------------------------------


@dataclass
class Spheres:
    """Collision spheres: carrying tree body (-1: fixed to the world), centre in that body frame."""

    body: np.ndarray
    centre: np.ndarray
    radius: np.ndarray
    names: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.radius)

    def concat(self, other: Spheres) -> Spheres:
        return Spheres(
            np.concatenate([self.body, other.body]),
            np.concatenate([self.centre, other.centre]),
            np.concatenate([self.radius, other.radius]),
            list(self.names) + list(other.names),
        )


def arm_spheres(robot: RobotModel) -> Spheres:
    """The planner's collision spheres of the arm, per tree body (-1: fixed to the world).

    They come from the sphere file named by `planner_spheres` in the robot's parameter file
    (path relative to the model file's folder): {links: {link: [{centre_m, radius_m}, ...]}},
    centres in the link frame. Never from the model's collision geometry: that is the arm's real
    shape, which the referee measures independently (tests check the spheres contain it).
    """
    from pathlib import Path

    import yaml
    from safesysid.systems.model.robot_model import ModelError, make_plant

    doc = robot.extra.get("params_doc") or {}
    if not doc.get("planner_spheres"):
        raise ModelError(
            f"{robot.source}: the robot's parameter file names no planner_spheres file "
            "(the planner over-approximates the arm with spheres)"
        )
    path = Path(robot.source).parent / doc["planner_spheres"]
    try:
        links = yaml.safe_load(path.read_text())["links"]
    except (OSError, yaml.YAMLError, KeyError, TypeError) as err:
        raise ModelError(f"{path}: cannot read the planner spheres ({err})") from err
    plant, scene_graph, _ = make_plant(robot.source, scene_graph=True)
    plant.Finalize()
    ctx = plant.CreateDefaultContext()
    body, centre, radius, names = [], [], [], []
    for link, spheres in links.items():
        if not plant.HasBodyNamed(link):
            raise ModelError(f"{path}: links.{link}: no such link in {robot.source}")
        drake_body = plant.GetBodyByName(link)
        idx = carrier_index(plant, drake_body, robot.body_names)
        carrier = plant.world_body() if idx < 0 else plant.GetBodyByName(robot.body_names[idx])
        x_cb = plant.CalcRelativeTransform(ctx, carrier.body_frame(), drake_body.body_frame())
        for k, sphere in enumerate(spheres):
            try:
                c, r = np.asarray(sphere["centre_m"], float), float(sphere["radius_m"])
            except (KeyError, TypeError, ValueError) as err:
                raise ModelError(f"{path}: links.{link}[{k}]: needs centre_m [x, y, z] and radius_m ({err})") from err
            if c.shape != (3,) or not r > 0:
                raise ModelError(f"{path}: links.{link}[{k}]: needs centre_m [x, y, z] and radius_m > 0")
            body.append(idx)
            centre.append(x_cb @ c)
            radius.append(r)
            names.append(f"{link}_sphere_{k}")
    _require_spheres_for_every_shape(plant, scene_graph, links, path)
    return Spheres(np.array(body, int), np.array(centre, float).reshape(-1, 3), np.array(radius, float), names)


def _require_spheres_for_every_shape(plant, scene_graph, links, path):
    """ModelError naming the sphere file when a link with collision geometry has no spheres (the
    planner would not see it; the referee would)."""
    from pydrake.geometry import Role
    from safesysid.systems.model.robot_model import ModelError

    inspector = scene_graph.model_inspector()
    shaped = {
        plant.GetBodyFromFrameId(inspector.GetFrameId(g)).name() for g in inspector.GetAllGeometryIds(Role.kProximity)
    }
    missing = sorted(shaped - set(links))
    if missing:
        raise ModelError(
            f"{path}: links: no spheres for {', '.join(missing)} (collision geometry in the model); "
            "python -m safesysid.models.cover_spheres MODEL writes them"
        )


def payload_spheres(robot: RobotModel, dumbbell: Dumbbell | None) -> Spheres:
    """Covering spheres of a dumbbell held at robot.extra['grasp_point'] (handle along EE x)."""
    if dumbbell is None:
        return Spheres(np.zeros(0, int), np.zeros((0, 3)), np.zeros(0), [])
    grasp = np.asarray(robot.extra.get("grasp_point", np.zeros(3)), float)
    spheres = dumbbell.covering_spheres()
    return Spheres(
        np.full(len(spheres), robot.end_effector, int),
        np.array([grasp + np.asarray(c) for c, _ in spheres]),
        np.array([r for _, r in spheres], float),
        [f"payload_{dumbbell.name}_{k}" for k in range(len(spheres))],
    )


def sphere_lipschitz(tree: regressors.KinematicTree, spheres: Spheres) -> np.ndarray:
    """L (m, n): bound of |d c_s / d q_j| over ALL configurations.

    Revolute: |z_j x (c - o_j)| <= |c - o_j| <= length of the fixed chain o_j -> child origin ->
    ... -> sphere centre (each link offset is a rigid translation). Prismatic: 1.
    """
    n = tree.n
    anc = tree.ancestors()
    t_pj = np.linalg.norm(tree.X_parent_joint[:, :3, 3], axis=1)
    t_jc = np.linalg.norm(tree.X_joint_child[:, :3, 3], axis=1)
    out = np.zeros((len(spheres), n))
    for s in range(len(spheres)):
        b = spheres.body[s]
        if b < 0:
            continue
        for j in np.flatnonzero(anc[:, b]):
            if tree.prismatic[j]:
                out[s, j] = 1.0
                continue
            # chain j -> b: joints strictly below j on the path to b
            path = [k for k in np.flatnonzero(anc[:, b]) if anc[j, k] and k != j]
            length = t_jc[j] + sum(t_pj[k] + t_jc[k] for k in path) + np.linalg.norm(spheres.centre[s])
            out[s, j] = length * (1 + 1e-12)
    return out


def local_spread(
    tree: regressors.KinematicTree,
    lipschitz: np.ndarray,
    jac_norm: np.ndarray,
    *,
    rho: np.ndarray,
    reach_radius: np.ndarray,
) -> np.ndarray:
    """spread (N, m) with |c_s(q) - c_s(q_mid)| <= spread for |q - q_mid| <= rho (per joint).

    |dc_s/dq_j| is the distance of c_s from axis j. Joints above j and j itself move c_s and the
    axis together (distance unchanged); a joint l below j moves c_s by at most L_sl |dq_l|. So on
    the box q_c +- reach_radius (which contains every segment used: all k, the tube):
        |dc_s/dq_j(q)| <= |dc_s/dq_j(q_c)| + sum_{l below j} L_sl reach_radius_l,
    capped by the global L_sj; the mean value theorem along the segment gives the spread.
    jac_norm (N, m, n) = |dc_s/dq_j| at q_c; rho, reach_radius (N, n).
    """
    below = tree.ancestors() & ~np.eye(tree.n, dtype=bool)  # [j, l]: joint l is below joint j
    drift = np.einsum("sl,nl,jl->nsj", lipschitz, reach_radius, below.astype(float))
    local = np.minimum(lipschitz[None], jac_norm + drift)
    return _up(_up(np.einsum("nsj,nj->ns", local, rho)) * (1 + 1e-12))


def sphere_centres(
    tree: regressors.KinematicTree, spheres: Spheres, q: np.ndarray, *, with_jacobian: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Centres (N, m, 3) in world and d c / d q (N, m, n, 3) at configurations q (N, n)."""
    kin = regressors.forward_kinematics(tree, q)
    nsamp = kin.p.shape[0]
    m = len(spheres)
    moving = spheres.body >= 0
    c = np.broadcast_to(spheres.centre, (nsamp, m, 3)).copy()
    b = spheres.body[moving]
    c[:, moving] = kin.p[:, b] + (kin.R[:, b] @ spheres.centre[moving][..., None])[..., 0]
    if not with_jacobian:
        return c, None
    anc = tree.ancestors()
    mask = np.zeros((m, tree.n))
    mask[moving] = anc[:, b].T
    w, u = kin.S[..., :3], kin.S[..., 3:]  # screw about O: point velocity = w x c + u
    jac = np.cross(w[:, None, :, :], c[:, :, None, :]) + u[:, None, :, :]
    return c, jac * mask[None, :, :, None]


@dataclass
class Boxes:
    """Oriented boxes: centre (m, 3), rotation box->world (m, 3, 3), half sizes (m, 3)."""

    centre: np.ndarray
    rotation: np.ndarray
    half_size: np.ndarray
    names: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.centre)

    @classmethod
    def from_obstacles(cls, obstacles: Sequence[Obstacle]) -> Boxes:
        """From scenario Obstacle records (xyz_m, rpy_rad, size_m), Drake's roll-pitch-yaw."""
        from pydrake.math import RollPitchYaw

        if not obstacles:
            return cls(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), [])
        return cls(
            np.array([o.xyz_m for o in obstacles], float),
            np.array([RollPitchYaw(o.rpy_rad).ToRotationMatrix().matrix() for o in obstacles]),
            0.5 * np.array([o.size_m for o in obstacles], float),
            [o.name for o in obstacles],
        )


def box_signed_distance(
    points: np.ndarray, centre: np.ndarray, rotation: np.ndarray, half_size: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance of points (P, 3) to boxes given per point (P, ...) and its gradient (P, 3)."""
    local = np.einsum("pji,pj->pi", rotation, points - centre)
    d = np.abs(local) - half_size
    outside = np.maximum(d, 0.0)
    dist_out = np.linalg.norm(outside, axis=1)
    inside = dist_out <= 0
    sd = np.where(inside, d.max(1), dist_out)
    g_out = outside * np.sign(local) / np.where(inside, 1.0, dist_out)[:, None]
    g_in = np.zeros_like(local)
    arg = d.argmax(1)
    g_in[np.arange(len(local)), arg] = np.sign(local[np.arange(len(local)), arg])
    grad_local = np.where(inside[:, None], g_in, g_out)
    return sd, np.einsum("pij,pj->pi", rotation, grad_local)


# ---------------------------------------------------------------------------------------------
# Time intervals of one plan: joint boxes, joint-limit box in k, state boxes for the torque check
# ---------------------------------------------------------------------------------------------


def _bezier_derivative(points, order, duration):
    deg = points.shape[0] - 1
    for r in range(order):
        points = (deg - r) * np.diff(points, axis=0)
    return points / duration**order


class PlanReach:
    """Per-interval over-approximations of one plan family (fixed start, k free in a box)."""

    def __init__(
        self,
        q0: ArrayLike,
        v0: ArrayLike,
        a0: ArrayLike,
        duration: float,
        k_center: ArrayLike,
        k_range: ArrayLike,
        num_intervals: int,
        bounds: TrackingBounds,
        *,
        restrictions: list[np.ndarray] | None = None,
    ) -> None:
        self.bezier = QuinticBezier(
            np.asarray(q0, float), np.asarray(v0, float), np.asarray(a0, float), float(duration)
        )
        self.n = len(self.bezier.q0)
        self.kc = np.asarray(k_center, float)
        self.kr = np.asarray(k_range, float)
        self.bounds = bounds
        self.T = float(duration)
        self.edges = np.linspace(0.0, self.T, num_intervals + 1)
        self.t_mid = 0.5 * (self.edges[:-1] + self.edges[1:])
        s_edges = self.edges / self.T
        # Restriction matrices per interval for degree 5, 4, 3 (position, velocity, acceleration).
        self._restrict = restrictions or [
            np.stack([restriction_matrix(5 - o, a, b) for a, b in zip(s_edges[:-1], s_edges[1:])]) for o in range(3)
        ]
        self.q_end0 = self.bezier.q0 + self.kc
        self.q_mid0, _, _ = self.bezier.evaluate(self.t_mid, self.q_end0)
        self.w_mid = QuinticBezier.end_weights(self.t_mid, self.T)[0]  # dq_mid / dq_end (scalar per interval)
        # k-independent deviation on each interval around its midpoint (hull property).
        p0 = self.bezier.control_points(self.q_end0)  # (6, n)
        sub = self._restrict[0] @ p0  # (nint, 6, n)
        dev_a = np.abs(sub - self.q_mid0[:, None, :]).max(1)
        wpts = self._restrict[0] @ np.array([0, 0, 0, 1, 1, 1.0])  # (nint, 6)
        dev_w = np.abs(wpts - self.w_mid[:, None]).max(1)
        dev = dev_a + dev_w[:, None] * self.kr[None, :]
        self.rho = _up(_up(dev * (1 + 1e-12)) + bounds.position[None, :])  # (nint, n)

    # -- centres -------------------------------------------------------------------------------
    def q_end(self, k: ArrayLike) -> np.ndarray:
        return self.q_end0 + self.kr * np.asarray(k, float)

    def k_of_q_end(self, q_end: ArrayLike) -> np.ndarray:
        return (np.asarray(q_end, float) - self.q_end0) / self.kr

    def q_mid(self, k: ArrayLike) -> np.ndarray:
        """(nint, n) joint-box centres; d q_mid[i, j] / d k_j = w_mid[i] * kr[j]."""
        return self.q_mid0 + self.w_mid[:, None] * (self.kr * np.asarray(k, float))[None, :]

    # -- joint limits -> box of k --------------------------------------------------------------
    def _affine_control_points(self, order):
        """fixed (nint, p, n), weight (nint, p): restricted control points = fixed + weight * q_end."""
        zero = _bezier_derivative(self.bezier.control_points(np.zeros(self.n)), order, self.T)
        one = _bezier_derivative(self.bezier.control_points(np.ones(self.n)), order, self.T)
        r = self._restrict[order]
        fixed = r @ zero
        weight = (r @ (one - zero))[..., 0]
        return fixed, weight

    def limit_box(self, joint_params: JointParameters) -> tuple[np.ndarray | None, np.ndarray | None, str]:
        """(k_lo, k_hi, reason): the box of k whose plans respect position and velocity limits
        for every t and every tracking error (reason is '' when not empty)."""
        qe_lo = self.q_end(-np.ones(self.n))
        qe_hi = self.q_end(np.ones(self.n))
        lo, hi = qe_lo.copy(), qe_hi.copy()
        checks = [
            (
                0,
                joint_params.position_lower + self.bounds.position,
                joint_params.position_upper - self.bounds.position,
                "position",
            ),
            (
                1,
                -joint_params.velocity_limit + self.bounds.velocity,
                joint_params.velocity_limit - self.bounds.velocity,
                "velocity",
            ),
        ]
        margin = 1e-9
        for order, low, high, what in checks:
            fixed, weight = self._affine_control_points(order)
            w = weight[..., None]
            for bound, sign in ((high - margin, 1.0), (low + margin, -1.0)):
                finite = np.isfinite(bound)
                # sign * (fixed + w x) <= sign * bound
                a = sign * fixed
                ws = sign * np.broadcast_to(w, fixed.shape)
                b = sign * bound
                with np.errstate(divide="ignore", invalid="ignore"):
                    lim = (b - a) / ws
                pos = (ws > 0) & finite
                neg = (ws < 0) & finite
                zero = (ws == 0) & finite
                if np.any(zero & (a > b)):
                    j = int(np.argwhere(zero & (a > b))[0, -1])
                    return (
                        None,
                        None,
                        (
                            f"joint {j + 1} {what} limit: the start state already violates the limit "
                            "shrunk by the tracking bound"
                        ),
                    )
                hi = np.minimum(hi, np.where(pos, lim, np.inf).min((0, 1)))
                lo = np.maximum(lo, np.where(neg, lim, -np.inf).max((0, 1)))
        k_lo, k_hi = self.k_of_q_end(lo), self.k_of_q_end(hi)
        k_lo, k_hi = np.maximum(k_lo, -1.0), np.minimum(k_hi, 1.0)
        bad = k_lo > k_hi
        if np.any(bad):
            j = int(np.flatnonzero(bad)[0])
            return (
                None,
                None,
                f"joint {j + 1}: no end position keeps the position/velocity limits with the tracking margin",
            )
        return k_lo, k_hi, ""

    # -- state boxes for every k in a box -------------------------------------------------------
    def desired_hulls(self, k_lo: ArrayLike, k_hi: ArrayLike) -> list[Interval]:
        """Intervals (nint, n) of the DESIRED q, qd, qdd over every t in I_i and k in [k_lo, k_hi] (hull of
        the restricted control points at both k ends: the control points are affine in each q_end_j)."""
        hulls = []
        for order in range(3):
            fixed, weight = self._affine_control_points(order)
            pts = [fixed + weight[..., None] * self.q_end(k)[None, None, :] for k in (k_lo, k_hi)]
            hulls.append(Interval(np.minimum(pts[0].min(1), pts[1].min(1)), np.maximum(pts[0].max(1), pts[1].max(1))))
        return hulls

    def state_boxes(self, k_lo: ArrayLike, k_hi: ArrayLike) -> tuple[Interval, Interval, Interval, Interval]:
        """Intervals (nint, n) of q, qd, qd_a, qdd_a covering every t in I_i, k in [k_lo, k_hi] and
        tracking error in the bound (the desired hulls padded by the tube)."""
        qd, vd, ad = self.desired_hulls(k_lo, k_hi)
        b = self.bounds

        def pad(x, r):
            return Interval(_down(_down(x.lo - r) - 1e-12 * np.abs(x.lo)), _up(_up(x.hi + r) + 1e-12 * np.abs(x.hi)))

        return pad(qd, b.position), pad(vd, b.velocity), pad(vd, b.qd_a), pad(ad, b.qdd_a)

    def tube_states(self, k_lo: ArrayLike, k_hi: ArrayLike, group: int = 1) -> tuple[Affine, Affine, Affine, Affine]:
        """Affine forms (affine_forms.tube_states) of q, qd, qd_a, qdd_a on hulls of `group` consecutive
        intervals: the tracking error kept as the shared symbols (e, r) instead of four independent boxes."""
        from safesysid.systems.planner.affine_forms import tube_states

        q_box = merge_rows(self.state_boxes(k_lo, k_hi)[0], group)
        _, vd, ad = (merge_rows(x, group) for x in self.desired_hulls(k_lo, k_hi))
        return tube_states(q_box, vd, ad, self.bounds)


def floor_exempt(tree: regressors.KinematicTree, spheres: Spheres) -> np.ndarray:
    """Spheres whose height no joint can change (world-fixed, or carried only by root joints with a
    vertical axis): the floor constraint is constant for them and the base sits on the floor."""
    out = np.zeros(len(spheres), bool)
    anc = tree.ancestors()
    for s in range(len(spheres)):
        b = spheres.body[s]
        if b < 0:
            out[s] = True
            continue
        joints = np.flatnonzero(anc[:, b])
        vertical = []
        for j in joints:
            if tree.parent[j] >= 0 or tree.prismatic[j]:
                vertical.append(False)
                continue
            axis_world = tree.X_parent_joint[j, :3, :3] @ tree.axis[j]
            vertical.append(abs(abs(axis_world[2]) - 1) < 1e-12)
        out[s] = all(vertical)
    return out
