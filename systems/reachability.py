"""Rigorous per-time-interval over-approximations of what the arm can reach while tracking a plan.

Pure math for the planner (systems/planner.py). A plan is the quintic Bézier of systems/bezier.py
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
4. Torque. The commanded input is u = W_p(q, qd, qd_a, qdd_a) theta0 + v with |v_j| <= lambda <=
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

from dataclasses import dataclass, field

import numpy as np

from . import regressors
from .armour import (
    TrackingBounds,  # the controller's certified bounds (position, velocity, qd_a, qdd_a)
    robust_gain_bound,
    spectral_bound,
)
from .bezier import QuinticBezier, restriction_matrix
from .intervals import Interval, _down, _up

# ---------------------------------------------------------------------------------------------
# Collision geometry: spheres on bodies, oriented boxes
# ---------------------------------------------------------------------------------------------


@dataclass
class Spheres:
    """Collision spheres: carrying tree body (-1: fixed to the world), centre in that body frame."""

    body: np.ndarray
    centre: np.ndarray
    radius: np.ndarray
    names: list = field(default_factory=list)

    def __len__(self):
        return len(self.radius)

    def concat(self, other):
        return Spheres(
            np.concatenate([self.body, other.body]),
            np.concatenate([self.centre, other.centre]),
            np.concatenate([self.radius, other.radius]),
            list(self.names) + list(other.names),
        )


def arm_spheres(robot):
    """The planner's collision spheres of the arm, per tree body (-1: fixed to the world).

    They come from the sphere file named by `planner_spheres` in the robot's parameter file
    (path relative to the model file's folder): {links: {link: [{centre_m, radius_m}, ...]}},
    centres in the link frame. Never from the model's collision geometry: that is the arm's real
    shape, which the referee measures independently (tests check the spheres contain it).
    """
    from pathlib import Path

    import yaml

    from .robot_model import ModelError, make_plant

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
    plant, _, _ = make_plant(robot.source)
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
    return Spheres(np.array(body, int), np.array(centre, float).reshape(-1, 3), np.array(radius, float), names)


def carrier_index(plant, body, body_names):
    """Tree index (in `body_names`) of the body that carries `body`: itself or the nearest body
    above it through welds; -1 when it is welded to the world (it never moves)."""
    inboard = {plant.get_joint(j).child_body().index(): plant.get_joint(j) for j in plant.GetJointIndices()}
    while body.name() not in body_names and body.index() in inboard:
        body = inboard[body.index()].parent_body()
    return body_names.index(body.name()) if body.name() in body_names else -1


def payload_spheres(robot, dumbbell):
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


def sphere_lipschitz(tree, spheres):
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


def local_spread(tree, lipschitz, jac_norm, rho, reach_radius):
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


def sphere_centres(tree, spheres, q, with_jacobian=True):
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
    names: list = field(default_factory=list)

    def __len__(self):
        return len(self.centre)

    @classmethod
    def from_obstacles(cls, obstacles):
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


def box_signed_distance(points, centre, rotation, half_size):
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
        self, q0, v0, a0, duration, k_center, k_range, num_intervals, bounds: TrackingBounds, restrictions=None
    ):
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
    def q_end(self, k):
        return self.q_end0 + self.kr * np.asarray(k, float)

    def k_of_q_end(self, q_end):
        return (np.asarray(q_end, float) - self.q_end0) / self.kr

    def q_mid(self, k):
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

    def limit_box(self, joint_params):
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
    def state_boxes(self, k_lo, k_hi):
        """Intervals (nint, n) of q, qd, qd_a, qdd_a covering every t in I_i, k in [k_lo, k_hi] and
        tracking error in the bound (hull of the restricted control points at both k ends: the
        control points are affine in each q_end_j)."""
        hulls = []
        for order in range(3):
            fixed, weight = self._affine_control_points(order)
            pts = [fixed + weight[..., None] * self.q_end(k)[None, None, :] for k in (k_lo, k_hi)]
            hulls.append(Interval(np.minimum(pts[0].min(1), pts[1].min(1)), np.maximum(pts[0].max(1), pts[1].max(1))))
        qd, vd, ad = hulls
        b = self.bounds

        def pad(x, r):
            return Interval(_down(_down(x.lo - r) - 1e-12 * np.abs(x.lo)), _up(_up(x.hi + r) + 1e-12 * np.abs(x.hi)))

        return pad(qd, b.position), pad(vd, b.velocity), pad(vd, b.qd_a), pad(ad, b.qdd_a)


# ---------------------------------------------------------------------------------------------
# Interval passivity regressor (local-frame RNEA over interval states), torque bound
# ---------------------------------------------------------------------------------------------


_REL = 5e-16  # > 2 units of roundoff: |fl(x) - x| <= u |x|, and the inflation step itself rounds


def _dn(x):
    """Cheap outward rounding (faster than nextafter): x - (5e-16 |x| + tiny) <= exact value."""
    return x - (np.abs(x) * _REL + 1e-300)


def _upr(x):
    return x + (np.abs(x) * _REL + 1e-300)


class _Box(Interval):
    """intervals.Interval for the RNEA below with cheaper outward rounding and no validation
    (measured: * 210 us vs 560 us, + 115 vs 355 us on (64, 10, 6)); sums add the k*eps*sum|x|
    accumulation bound. mid, mag, shape are Interval's."""

    def __init__(self, lo, hi=None):
        self.lo = np.asarray(lo, float)
        self.hi = self.lo if hi is None else np.asarray(hi, float)

    @property
    def rad(self):
        return _upr(0.5 * (self.hi - self.lo))

    def __getitem__(self, idx):
        return _Box(self.lo[idx], self.hi[idx])

    def __neg__(self):
        return _Box(-self.hi, -self.lo)

    def __add__(self, o):
        if isinstance(o, _Box):
            return _Box(_dn(self.lo + o.lo), _upr(self.hi + o.hi))
        return _Box(_dn(self.lo + o), _upr(self.hi + o))

    __radd__ = __add__

    def __sub__(self, o):
        if isinstance(o, _Box):
            return _Box(_dn(self.lo - o.hi), _upr(self.hi - o.lo))
        return _Box(_dn(self.lo - o), _upr(self.hi - o))

    def __mul__(self, o):
        if isinstance(o, _Box):
            p1, p2, p3, p4 = self.lo * o.lo, self.lo * o.hi, self.hi * o.lo, self.hi * o.hi
            return _Box(
                _dn(np.minimum(np.minimum(p1, p2), np.minimum(p3, p4))),
                _upr(np.maximum(np.maximum(p1, p2), np.maximum(p3, p4))),
            )
        p1, p2 = self.lo * o, self.hi * o
        return _Box(_dn(np.minimum(p1, p2)), _upr(np.maximum(p1, p2)))

    __rmul__ = __mul__

    def sum(self, axis):
        k = self.lo.shape[axis]
        err = (k * np.finfo(float).eps) * self.mag.sum(axis)
        return _Box(_dn(self.lo.sum(axis) - err), _upr(self.hi.sum(axis) + err))


def _stack(items, axis=-1):
    return _Box(np.stack([x.lo for x in items], axis), np.stack([x.hi for x in items], axis))


# Interval twins of regressors.py's cross products (same formulas on _Box; exact per component).
def _cross(a, b):
    """Interval cross product over the last axis (length 3)."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return _stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx])


def _matvec(m, x):
    """(..., 3, 3) interval matrix times (..., 3) interval vector."""
    return (m * x[..., None, :]).sum(-1)


def _tmatvec(m, x):
    """m^T x."""
    return (m * x[..., :, None]).sum(-2)


def _motion_cross(v, m):
    w, u = v[..., :3], v[..., 3:]
    return _cat([_cross(w, m[..., :3]), _cross(w, m[..., 3:]) + _cross(u, m[..., :3])])


def _force_cross(v, f):
    w, u = v[..., :3], v[..., 3:]
    return _cat([_cross(w, f[..., :3]) + _cross(u, f[..., 3:]), _cross(w, f[..., 3:])])


def _cat(items):
    return _Box(np.concatenate([x.lo for x in items], -1), np.concatenate([x.hi for x in items], -1))


def signed_selection(tensor):
    """(comp, sign) such that x @ tensor.reshape(k, -1) == x[..., comp] * sign, for a constant
    linear map (k, ...) whose every output entry is +-one input component or 0 (K(x), x x*):
    a gather instead of a product, exact, any dtype, interval-friendly."""
    flat = np.asarray(tensor, float).reshape(len(tensor), -1)
    if not (np.all(np.isin(flat, (-1.0, 0.0, 1.0))) and np.all((flat != 0).sum(0) <= 1)):
        raise ValueError("not a signed selection")
    return np.abs(flat).argmax(0), flat.sum(0)


# K(x) of regressors.inertia_times, transposed to (..., 10, 6): column c of the 6x10 regressor is [..., c, :].
_K_COMP, _K_SIGN = signed_selection(np.swapaxes(regressors.inertia_times(np.eye(6)), 1, 2))


def _inertia_times(x):
    """Interval K(x) stored as (..., 10, 6) (exact: every entry is +-one component of x)."""
    lo, hi = x.lo[..., _K_COMP], x.hi[..., _K_COMP]
    shape = x.shape[:-1] + (10, 6)
    return _Box(
        np.where(_K_SIGN > 0, lo, np.where(_K_SIGN < 0, -hi, 0.0)).reshape(shape),
        np.where(_K_SIGN > 0, hi, np.where(_K_SIGN < 0, -lo, 0.0)).reshape(shape),
    )


def _body_wrench_regressor(v, va, a):
    """Interval Y (..., 10, 6) with Y theta = I a + B(v) va (regressors.body_wrench_regressor)."""
    kv, kva = _inertia_times(v), _inertia_times(va)
    v_, va_ = v[..., None, :], va[..., None, :]
    return _inertia_times(a) + 0.5 * (
        _force_cross(v_, kva) + _force_cross(va_, kv) - _inertia_times(_motion_cross(v, va))
    )


def _joint_transforms(tree, q):
    """Interval E (N, n, 3, 3) (parent->child rotation of coordinates) and r (N, n, 3) (child
    origin in parent coords) of each joint, entries affine in sin q, cos q (Rodrigues)."""
    n = tree.n
    s, c = _sin_cos(q)
    es, rs = [], []
    for i in range(n):
        rp, tp = tree.X_parent_joint[i, :3, :3], tree.X_parent_joint[i, :3, 3]
        rc, tc = tree.X_joint_child[i, :3, :3], tree.X_joint_child[i, :3, 3]
        if tree.prismatic[i]:
            rot = _Box(np.broadcast_to(rp @ rc, (q.shape[0], 3, 3)))
            pos = q[:, i, None] * (rp @ tree.axis[i]) + (tp + rp @ tc)
        else:
            k = regressors.skew(tree.axis[i])
            # R_parent_child = rp (I + s K + (1 - c) K^2) rc = A0 + s A1 + c A2
            a0 = rp @ (np.eye(3) + k @ k) @ rc
            a1 = rp @ k @ rc
            a2 = -rp @ k @ k @ rc
            si, ci = s[:, i, None, None], c[:, i, None, None]
            rot = _affine3(a0, a1, a2, si, ci)
            b0 = tp + rp @ (np.eye(3) + k @ k) @ tc
            b1 = rp @ k @ tc
            b2 = -rp @ k @ k @ tc
            pos = _affine3(b0, b1, b2, s[:, i, None], c[:, i, None])
        # E = R_parent_child^T: child coords of a parent-coords vector.
        es.append(_Box(np.swapaxes(rot.lo, -1, -2), np.swapaxes(rot.hi, -1, -2)))
        rs.append(pos)
    return _stack(es, 1), _stack(rs, 1)


def _affine3(a0, a1, a2, s, c):
    """a0 + s a1 + c a2 with interval s, c (exact per entry: s, c independent), outward."""
    mid = a0 + s.mid * a1 + c.mid * a2
    rad = np.abs(a1) * s.rad + np.abs(a2) * c.rad
    err = 4 * np.finfo(float).eps * (np.abs(a0) + np.abs(a1) * s.mag + np.abs(a2) * c.mag)
    return _Box(_down(mid - rad - err), _up(mid + rad + err))


def _sin_cos(q):
    from . import intervals

    s, c = intervals.sin(Interval(q.lo, q.hi)), intervals.cos(Interval(q.lo, q.hi))
    return _Box(s.lo, s.hi), _Box(c.lo, c.hi)


def _to_child(e, r, x):
    """Motion vector from parent to child coordinates: w' = E w, u' = E (u - r x w)."""
    w, u = x[..., :3], x[..., 3:]
    return _cat([_matvec(e, w), _matvec(e, u - _cross(r, w))])


def _force_to_parent(e, r, f):
    """Force vector from child to parent coordinates: f_p = E^T f, n_p = E^T n + r x f_p."""
    n_, f_ = f[..., :3], f[..., 3:]
    fp = _tmatvec(e, f_)
    return _cat([_tmatvec(e, n_) + _cross(r, fp), fp])


def _joint_screws(tree):
    """Joint motion subspaces (n, 6) in child-body coordinates (constant)."""
    s_local = np.zeros((tree.n, 6))
    for i in range(tree.n):
        rc, tc = tree.X_joint_child[i, :3, :3], tree.X_joint_child[i, :3, 3]
        ax = tree.axis[i]
        if tree.prismatic[i]:
            s_local[i, 3:] = rc.T @ ax
        else:
            # axis through the joint origin, which sits at -rc^T tc in child coordinates
            w = rc.T @ ax
            s_local[i, :3] = w
            s_local[i, 3:] = np.cross(-rc.T @ tc, w)
    return s_local


def interval_body_jacobians(tree, q):
    """Interval body Jacobians (N, n_bodies, n, 6): [row, i, j] = twist of body i (its own
    coordinates) per unit velocity of joint j, over the configuration boxes q (Interval (N, n));
    the velocity pass of the local-frame RNEA below with one unit velocity per joint at once."""
    n = tree.n
    q = _Box(q.lo, q.hi)
    nsamp = q.shape[0]
    e, r = _joint_transforms(tree, q)
    s_local = _joint_screws(tree)
    unit = np.eye(n)[None, :, :, None]  # [., j, i, .] = 1 when j == i
    jac = [None] * n
    for i in range(n):
        own = _Box(np.broadcast_to(unit[:, :, i] * s_local[i], (nsamp, n, 6)))
        par = tree.parent[i]
        jac[i] = own if par < 0 else _to_child(e[:, i, None], r[:, i, None], jac[par]) + own
    return Interval(np.stack([x.lo for x in jac], 1), np.stack([x.hi for x in jac], 1))


# V^T I(theta) V = sum_k theta_k V^T Q_k V for a body-frame spatial inertia (regressors.inertia_times).
_INERTIA_FORMS = np.einsum("bak->kab", regressors.inertia_times(np.eye(6)))  # [k, a, b] = K(e_b)[a, k]
_INERTIA_FORMS = 0.5 * (_INERTIA_FORMS + np.swapaxes(_INERTIA_FORMS, 1, 2))


def interval_mass_spread(robot, q, theta_lo, theta_hi):
    """mu (N,) >= controller.mass_spread(q') for every q' in each configuration box q (Interval (N, n)).

    r^T M r = sum_i (J_i r)^T I_i (J_i r) + sum_j Ia_j r_j^2 (J_i: body Jacobians), so
    dM/dtheta_k = J_i^T Q_k J_i for body i's parameters and e_j e_j^T for Ia_j. With J = Jc + D,
    |D| <= rad(J) over the box: |J^T Q J| <= |Jc^T Q Jc| + |Jc|^T |Q| rad + rad^T |Q| (|Jc| + rad)
    (centred form: the box's width enters to first order). Then as controller.mass_spread:
    mu <= lambda_max(sum_k width_k |dM/dtheta_k|)."""
    n = robot.n
    width = np.asarray(theta_hi, float) - np.asarray(theta_lo, float)
    jac = interval_body_jacobians(robot.tree, q)
    mid = 0.5 * (jac.lo + jac.hi)
    jc = np.swapaxes(mid, -1, -2)  # (N, n_bodies, 6, n)
    rad = np.swapaxes(_up(np.maximum(jac.hi - mid, mid - jac.lo)), -1, -2)  # |J - Jc| <= rad on the box
    forms = np.abs(_INERTIA_FORMS)
    spread = np.zeros((q.shape[0], n, n))
    for i in range(n):
        w = width[10 * i : 10 * i + 10]
        jci, radi = jc[:, i], rad[:, i]
        centre = np.abs(np.swapaxes(jci, -1, -2)[:, None] @ (_INERTIA_FORMS @ jci[:, None]))  # (N, 10, n, n)
        absj = np.abs(jci)
        first = np.swapaxes(absj, -1, -2)[:, None] @ (forms @ radi[:, None])
        second = np.swapaxes(radi, -1, -2)[:, None] @ (forms @ (absj + radi)[:, None])
        scale = np.swapaxes(absj, -1, -2)[:, None] @ (forms @ absj[:, None])
        bound = centre + first + second + 64 * np.finfo(float).eps * scale  # + rounding of the products
        spread += np.einsum("xkab,k->xab", bound, w)
    ia = width[10 * n + 2 :: 4]
    spread[:, np.arange(n), np.arange(n)] += ia
    return spectral_bound(spread)


def interval_passivity_regressor(robot, q, v, va, aa, gravity=True):
    """Interval Wp (N, n, 14n) enclosing RobotModel.passivity_regressor over boxes q, v, va, aa
    (Intervals (N, n)). Local-frame RNEA: each body's velocity/acceleration from its parent's
    through one interval joint transform; the body wrench regressors carried back up the tree."""
    tree = robot.tree
    n = tree.n
    q, v, va, aa = (_Box(x.lo, x.hi) for x in (q, v, va, aa))
    nsamp = q.shape[0]
    e, r = _joint_transforms(tree, q)
    s_local = _joint_screws(tree)
    g_world = np.concatenate([np.zeros(3), -tree.gravity if gravity else np.zeros(3)])  # base "acceleration"
    vel, vela, acc = [None] * n, [None] * n, [None] * n
    ys = [None] * n
    for i in range(n):
        par = tree.parent[i]
        ei, ri = e[:, i], r[:, i]
        if par < 0:
            v_par = _Box(np.zeros((nsamp, 6)))
            va_par = v_par
            a_par = _Box(np.broadcast_to(g_world, (nsamp, 6)))
        else:
            v_par, va_par, a_par = vel[par], vela[par], acc[par]
        si = _Box(s_local[i])[None]
        vp_c = _to_child(ei, ri, v_par)
        vel[i] = vp_c + si * v[:, i, None]
        vela[i] = _to_child(ei, ri, va_par) + si * va[:, i, None]
        # a_i = X a_par + s aa_i + v_i x s va_i
        acc[i] = _to_child(ei, ri, a_par) + si * aa[:, i, None] + _motion_cross(vel[i], si * va[:, i, None])
        ys[i] = _body_wrench_regressor(vel[i], vela[i], acc[i])  # (N, 10, 6)
    lo = np.zeros((nsamp, n, 14 * n))
    hi = np.zeros((nsamp, n, 14 * n))
    for i in range(n):  # body i's wrench columns carried up to every joint above it
        f = ys[i]
        j = i
        while j >= 0:
            col = (f * s_local[j][None, None]).sum(-1)  # (N, 10)
            lo[:, j, 10 * i : 10 * i + 10], hi[:, j, 10 * i : 10 * i + 10] = col.lo, col.hi
            par = tree.parent[j]
            if par < 0:
                break
            f = _force_to_parent(e[:, j, None], r[:, j, None], f)
            j = par
    # Friction columns [Fc, Fv, Ia, beta] per joint.
    vs = robot.coulomb_smoothing
    if vs > 0:
        sgn = _Box(
            np.maximum(_down(np.tanh(va.lo / vs)) - 1e-15, -1.0), np.minimum(_up(np.tanh(va.hi / vs)) + 1e-15, 1.0)
        )
    else:
        sgn = _Box(np.sign(va.lo), np.sign(va.hi))
    idx = np.arange(n)
    base = 10 * n + 4 * idx
    for off, x in ((0, sgn), (1, va), (2, aa), (3, _Box(np.ones((nsamp, n))))):
        lo[:, idx, base + off], hi[:, idx, base + off] = x.lo, x.hi
    return Interval(lo, hi)


def robust_bound_vertex(robot, q, v, va, aa, theta0, theta_lo, theta_hi, block, full=None, b_rows=1):
    """Tighter w_bar (N, n) for the parameters in `block` (e.g. the end effector's 10).

    W_p is affine in aa: W_p = A(q, v, va) + sum_j B_j(q) aa_j (B_j: the M(q) columns, no gravity,
    no velocity). sum_k |W_p,ik| d_k is convex in aa, so its max over the aa box is at a vertex;
    with interval A, B_j over the rest of the box, the max over the 2^n aa vertices of
    sum_k d_k mag(A_ik + sum_j B_j,ik aa_j) bounds it. Parameters outside `block` use the plain
    sum_k mag(W_p,ik) d_k. B_j depends on q only: it is evaluated on hulls of `b_rows`
    consecutive q boxes (cheap, q moves little). Returns (w_bar (N, n), plain w_bar (N, n)).
    """
    n = robot.n
    nb = q.shape[0]
    theta0 = np.asarray(theta0, float)
    d = np.maximum(np.maximum(np.asarray(theta_hi, float) - theta0, theta0 - np.asarray(theta_lo, float)), 0.0)
    a_part = interval_passivity_regressor(robot, q, v, va, Interval(np.zeros((nb, n))))
    # B_j: unit aa_j, no gravity, no velocity, on the q hulls; batched over j.
    q_hull = merge_rows(q, b_rows)
    ng = q_hull.shape[0]
    zeros = Interval(np.zeros((n * ng, n)))
    b_all = interval_passivity_regressor(
        robot,
        Interval(np.tile(q_hull.lo, (n, 1)), np.tile(q_hull.hi, (n, 1))),
        zeros,
        zeros,
        Interval(np.repeat(np.eye(n), ng, axis=0)),
        gravity=False,
    )
    cols = np.zeros(a_part.lo.shape[-1], bool)
    cols[block] = True
    fr = 10 * n + 4 * np.arange(n)
    cols[fr] = cols[fr + 1] = cols[fr + 2] = cols[fr + 3] = False  # friction: bounded plainly
    owner = np.arange(nb) // b_rows
    a_lo, a_hi = a_part.lo[..., cols], a_part.hi[..., cols]  # (N, n, p)
    b_lo = b_all.lo[..., cols].reshape(n, ng, n, -1)[:, owner]  # (j, N, n, p)
    b_hi = b_all.hi[..., cols].reshape(n, ng, n, -1)[:, owner]
    # Every vertex at once: the sums over j for all 2^n choices of aa_j in {lo, hi}, by doubling.
    lo, hi = a_lo[None], a_hi[None]
    scale = np.maximum(np.abs(a_lo), np.abs(a_hi))
    for j in range(n):
        opts_lo, opts_hi = [], []
        for x in (aa.lo[:, j], aa.hi[:, j]):
            p1, p2 = b_lo[j] * x[:, None, None], b_hi[j] * x[:, None, None]
            opts_lo.append(np.minimum(p1, p2))
            opts_hi.append(np.maximum(p1, p2))
        lo = np.concatenate([lo + opts_lo[0], lo + opts_lo[1]])
        hi = np.concatenate([hi + opts_hi[0], hi + opts_hi[1]])
        scale = scale + np.maximum(
            np.maximum(np.abs(b_lo[j]), np.abs(b_hi[j]))
            * np.maximum(np.abs(aa.lo[:, j]), np.abs(aa.hi[:, j]))[:, None, None],
            0,
        )
    err = 4 * (n + 2) * np.finfo(float).eps * scale  # rounding of the sums above
    mag = np.maximum(np.abs(lo), np.abs(hi)) + err[None]
    best = _up((mag @ d[cols]).max(0) * (1 + 32 * np.finfo(float).eps))
    full = interval_passivity_regressor(robot, q, v, va, aa) if full is None else full
    rest = full.mag[..., ~cols] @ d[~cols]
    plain = full.mag @ d
    return _up(np.minimum(plain, best + rest)), plain


def barrier_excess(robot, q, theta_lo, theta_hi, bounds: TrackingBounds, rows=1):
    """(N,): alpha eps mu / 2 over each configuration box, the amount by which the controller's
    lambda may exceed |w_bar| on the tube (controller.robust_gain_bound); mu on hulls of `rows`
    consecutive boxes (it varies slowly; fewer, slightly larger boxes)."""
    if bounds.eps == 0 or bounds.alpha == 0:
        return np.zeros(q.shape[0])
    mu = interval_mass_spread(robot, merge_rows(q, rows), theta_lo, theta_hi)[np.arange(q.shape[0]) // rows]
    return robust_gain_bound(np.zeros_like(mu), bounds.alpha, bounds.eps, mu)


def torque_bound(wp, theta0, theta_lo, theta_hi, excess):
    """sup |u| per (interval, joint) over the boxes of wp (Interval (N, n, p)).

    u = W_p theta0 + v, |v_j| <= lambda <= ||w_bar||_2 + excess (excess (N,) from barrier_excess
    on the same boxes), w_bar_i <= sum_k |W_p,ik| d_k with d = max(theta_hi - theta0, theta0 - theta_lo).
    Returns (sup|u| (N, n), nominal part, robust part (N,)).
    """
    theta0 = np.asarray(theta0, float)
    d = np.maximum(np.asarray(theta_hi, float) - theta0, theta0 - np.asarray(theta_lo, float))
    d = np.maximum(d, 0.0)
    mid = wp.mid @ theta0
    rad = wp.rad @ np.abs(theta0)
    err = 8 * np.finfo(float).eps * (wp.mag @ np.abs(theta0))
    nominal = _up(np.abs(mid) + rad + err)
    wbar = _up((wp.mag @ d) * (1 + 1e-12))
    robust = robust_term(wbar, excess)
    return _up(nominal + robust[:, None]), nominal, robust


def robust_term(w_bar, excess):
    """Rounded-up ||w_bar||_2 (last axis) + excess: the bound of the controller's |v_j| <= lambda."""
    return _up(_up(np.linalg.norm(w_bar, axis=-1) * (1 + 1e-12)) + excess)


def merge_rows(box, group):
    """Hull of consecutive groups of `group` rows of an Interval (rows, n) (the last group padded
    with the last row)."""
    rows = box.lo.shape[0]
    pad = (-rows) % group
    lo = np.concatenate([box.lo, np.repeat(box.lo[-1:], pad, 0)]).reshape(-1, group, box.lo.shape[1])
    hi = np.concatenate([box.hi, np.repeat(box.hi[-1:], pad, 0)]).reshape(-1, group, box.hi.shape[1])
    return Interval(lo.min(1), hi.max(1))
