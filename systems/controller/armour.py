"""ARMOUR robust passivity controller: the control law, its interval bounds and the ultimate
tracking bound (pure math; the LeafSystems in controller_systems.py are thin wrappers).

Law (reference-notes.md, "Robust passivity controller"):
    e = q_d - q (wrapped on continuous joints), edot = qd_d - qd,
    qd_a = qd_d + Kr e,  qdd_a = qdd_d + Kr edot,  r = edot + Kr e
    tau_nom = Wp(q, qd, qd_a, qdd_a) theta0                     (C Christoffel: Mdot - 2C skew)
    [tau]   = Wp [theta]  (exact hull: linear in theta)         w_bar_i = max(sup - nom, nom - inf)
    V_bar   = max over [theta] of 1/2 r^T Wm(q, r) theta        (exact: linear in theta)
    h = V_max - V_bar,  lambda = max(0, -alpha h/|r| + |w_bar|),  v = lambda r/|r|,  u = tau_nom + v.

Why it works: with the true theta in [theta], w = tau(theta) - tau_nom has |w_i| <= w_bar_i, and
along the closed loop (V = 1/2 r^T M(q; theta_true) r, the TRUE value; continuous time)
    dV/dt <= r^T (w - v) - r^T dF <= |r| (|w_bar| - lambda) <= alpha h <= alpha (V_max - V)
(dF = friction(qd_a) - friction(qd) is monotone in r, so dissipative; h <= V_max - V as
V_bar >= V), hence V(t) <= V_max whenever V(0) <= V_max. Sampling: see "Sampling" below.

Bound of the robust input on the tube (what the planner's torque bound uses; `robust_gain_bound`).
V_bar is a maximum over the box, so h < 0 happens while the true V <= V_max; there
    -h = V_bar - V_max <= V_bar - V = max_[theta] 1/2 r^T (M(q; theta) - M(q; theta_true)) r
       <= 1/2 sum_k width_k |r^T dM/dtheta_k(q) r| <= 1/2 |r|^2 mu(q)            (`mass_spread`)
with mu(q) = lambda_max(sum_k width_k |dM/dtheta_k(q)|) (entrywise |.|; |u^T A u| <= |u|^T |A| |u|), so
    lambda = |w_bar| - alpha h/|r| <= |w_bar| + (alpha/2) |r| mu(q) <= |w_bar| + (alpha/2) eps mu(q),
and |v_j| <= lambda. The planner adds (alpha/2) eps mu over each interval's configuration box
(reachability.barrier_excess) to |w_bar|.

Sampling (an assumption, measured, not proven). The loop runs at the plant step dt
(plant.time_step_s) with the input held. Over a step, r moves by about dt |w - v| / sigma_min;
at the boundary (h <= 0, so lambda >= |w_bar| and a = -r_hat^T (w - v) >= 0) |w - v|^2 <=
2 a lambda, so to leading order
    V(t_k + s) - V(t_k) <= s a (-|r| + s lambda / sigma_min)   (s <= dt),
i.e. the held robust input cannot push V out while dt <= sigma_min rho_min / lambda, rho_min =
eps sqrt(sigma_min / lambda_max(M)) the smallest |r| on the boundary. The other O(dt) terms (the
drift of tau_nom and of the true torque along the step) meet the viscous dissipation
r^T dF >= Fv_min |r|^2, which the continuous argument does not use. This leading-order limit
is 11-13 ms for the adversarial runs of tests/test_tracking_bound.py (boundary starts, h = 0);
those runs keep V <= V_max at 1 ms (the scenario's step; the hardware runs >= 1 kHz) and leave
the tube at 40 ms (the test that shows the check can fail); the sweep test_step_size_margin
(SAFESYSID_FULL=1) measures: held up to 25 ms, V = 1.84 V_max at 30 ms. Assumption used
everywhere: dt <= 1 ms (a margin of ~10x on the leading-order limit, 25x on the measured one).

Friction in tau_nom is evaluated at (qd_a, qdd_a) as in RobotModel.passivity_regressor; that is
safe because the Coulomb law Fc tanh(v/vs) and Fv v are monotone, so r^T dF >= 0 above.

The per-sample regressors come from `ControllerDynamics`, an exact re-arrangement of
systems/model/regressors.py for one sample (batched over bodies, bilinear maps as constant tensors):
Wp and Wm together in ~0.3 ms instead of ~4 ms for the two vectorized calls at N = 1, which is
what lets the loop run at 1 kHz in real time; tests check it equals RobotModel's to 1e-11.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import accumulate
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.math.intervals import Interval, dot_rounding, matmul
from safesysid.systems.math.spatial import cross_rows
from safesysid.systems.model import regressors

if TYPE_CHECKING:
    from safesysid.systems.model.robot_model import RobotModel

_TINY_R = 1e-9  # below this |r| the direction r/|r| is meaningless and lambda is 0 anyway
_UP = 1 + 8 * np.finfo(float).eps  # outward factor for the few float sums done here


def friction_index(n: int, joint: int, name: str) -> int:
    """Index of a friction parameter ('Fc', 'Fv', 'Ia', 'beta') of `joint` in theta (14 n)."""
    return 10 * n + 4 * joint + ("Fc", "Fv", "Ia", "beta").index(name)


# Spatial algebra as constant tensors, built once from regressors.py's definitions: every
# bilinear map becomes one matrix product on the outer product of its arguments (at a single
# sample, numpy call overhead dominates, so fewer and larger calls win).
_E6 = np.eye(6)
_CROSS_MOTION = np.stack([regressors.cross_motion(_E6[k], _E6) for k in range(6)]).reshape(36, 6)
_INERTIA = regressors.inertia_times(_E6).reshape(6, 60)  # K(x) = x @ _INERTIA  (6 x 10 blocks)
# B(v) va = 1/2 [v x* K(va) + va x* K(v) - K(v x va)]  (Christoffel form, regressors.py)
_BILINEAR = regressors.body_wrench_regressor(
    _E6[:, None].repeat(6, 1), _E6[None, :].repeat(6, 0), np.zeros((6, 6, 6))
).reshape(36, 60)
_SKEW = regressors.skew(np.eye(3)).reshape(3, 9)  # [p]x = p @ _SKEW (as 3 x 3; linear in p)


def _outer(a, b):
    """Row-wise outer products (m, 6) x (m, 6) -> (m, 36)."""
    return (a[:, :, None] * b[:, None, :]).reshape(len(a), -1)


# ---- fast single-sample regressors ---------------------------------------------------------------
class ControllerDynamics:
    """Wp(q, v, va, aa) and Wm(q, x) of a RobotModel for ONE sample, kinematics shared.

    Same quantities as RobotModel.passivity_regressor / momentum_regressor (tests compare them
    to 1e-12); only the order of evaluation differs: poses by a short loop, everything else as
    one batch over bodies, with the ancestor matrix doing the tree sums.
    """

    def __init__(self, robot: RobotModel) -> None:
        tree = robot.tree
        if np.any(tree.prismatic):
            raise NotImplementedError("ControllerDynamics handles revolute joints only")
        self.robot = robot
        self.n = n = tree.n
        self.parent = tree.parent.copy()
        self.anc_t = tree.ancestors().T.astype(float)  # [i, j] = 1 when joint j moves body i
        self.anc = self.anc_t.T.copy()
        self.axis = tree.axis.copy()
        k = regressors.skew(self.axis)
        self.k1, self.k2 = k, k @ k
        self.gravity_acc = np.concatenate([np.zeros(3), -tree.gravity])  # base acceleration
        self.smoothing = robot.coulomb_smoothing
        self.has_parent = (self.parent >= 0)[:, None]
        self.parent_idx = np.where(self.parent >= 0, self.parent, 0)
        self.idx = np.arange(n)
        self.x_pj = tree.X_parent_joint.copy()
        self.x_jc = tree.X_joint_child.copy()
        self._eye4 = np.tile(np.eye(4), (n, 1, 1))
        self.serial = bool(np.all(self.parent == np.arange(n) - 1))  # a chain: cumulative product

    def _poses(self, q):
        """Body rotations R (n,3,3), origins p (n,3) and joint screws S (n,6) about O."""
        n = self.n
        s, c = np.sin(q), np.cos(q)
        # Homogeneous transform of body i in its carrier body: X_pj Rot(q_i) X_jc (batched).
        rot = self._eye4.copy()
        rot[:, :3, :3] += s[:, None, None] * self.k1 + (1 - c)[:, None, None] * self.k2
        G = self.x_pj @ rot @ self.x_jc
        if self.serial:
            H = np.array(list(accumulate(G, np.matmul)))
        else:
            H = np.empty((n, 4, 4))
            for i in range(n):
                H[i] = G[i] if self.parent[i] < 0 else H[self.parent[i]] @ G[i]
        F = np.where(self.has_parent[:, :, None], H[self.parent_idx], np.eye(4)) @ self.x_pj  # joint frames
        z = (F[:, :3, :3] @ self.axis[:, :, None])[:, :, 0]
        S = np.concatenate([z, cross_rows(F[:, :3, 3], z)], -1)
        return H[:, :3, :3], H[:, :3, 3], S

    def regressors(
        self, q: ArrayLike, v: ArrayLike, va: ArrayLike, *, aa: ArrayLike, x: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray]:
        """(Wp, Wm): Wp theta = M aa + C(q, v) va + g + F(va, aa); Wm theta = (M + diag Ia) x."""
        q, v, va, aa, x = (np.asarray(a, float).reshape(-1) for a in (q, v, va, aa, x))
        n = self.n
        R, p, S = self._poses(q)
        # Twists of v, va and x at once: [k, i] = sum over ancestors j of i of S_j x_k,j.
        V, vel_a, vel_x = np.einsum("ij,kj,jl->kil", self.anc_t, np.stack([v, va, x]), S)
        v_par = np.where(self.has_parent, V[self.parent_idx], 0.0)
        Sdot = _outer(v_par, S) @ _CROSS_MOTION  # dS_j/dt = V_parent(j) x S_j
        acc_a = self.gravity_acc + self.anc_t @ (S * aa[:, None] + Sdot * va[:, None])
        # Plucker transforms world (about O) -> body i: [w; u] -> [R^T w; R^T (u + w x p)].
        rt = np.swapaxes(R, 1, 2)
        X = np.zeros((n, 6, 6))
        X[:, :3, :3] = rt
        X[:, 3:, 3:] = rt
        X[:, 3:, :3] = rt @ -(p @ _SKEW).reshape(n, 3, 3)  # R^T (w x p) = R^T (-[p]x) w
        world = np.concatenate([np.stack([V, vel_a, acc_a, vel_x], 2), np.broadcast_to(S.T, (n, 6, n))], 2)
        body = X @ world  # (n, 6, 4 + n)
        vb, vab, ab, xb = body[:, :, 0], body[:, :, 1], body[:, :, 2], body[:, :, 3]
        s_body = np.swapaxes(body[:, :, 4:], 1, 2) * self.anc_t[:, :, None]  # [i, j] = X_i S_j, ancestors
        # Body regressors: I a + B(v) va (passivity) and I x (momentum), each (n, 6, 10).
        y_p = (ab @ _INERTIA + _outer(vb, vab) @ _BILINEAR).reshape(n, 6, 10)
        y_m = (xb @ _INERTIA).reshape(n, 6, 10)
        out = np.zeros((2, n, 14 * n))
        out[:, :, : 10 * n] = np.einsum("ijk,bikl->bjil", s_body, np.stack([y_p, y_m])).reshape(2, n, 10 * n)
        idx, f0 = self.idx, 10 * n + 4 * self.idx
        out[0, idx, f0] = regressors.coulomb_shape(va, self.smoothing)
        out[0, idx, f0 + 1] = va
        out[0, idx, f0 + 2] = aa
        out[0, idx, f0 + 3] = 1.0
        out[1, idx, f0 + 2] = x
        return out[0], out[1]

    def gravity(self, q: ArrayLike, theta: ArrayLike) -> np.ndarray:
        """g(q; theta) + beta (the passivity regressor at rest) (n,)."""
        zero = np.zeros(self.n)
        wp, _ = self.regressors(q, zero, zero, aa=zero, x=zero)
        return wp @ theta


# ---- the law ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ArmourGains:
    Kr: np.ndarray  # (n,) 1/s
    alpha: float  # 1/s
    V_max: float  # J


@dataclass
class TrackingErrors:
    e: np.ndarray
    edot: np.ndarray
    qd_a: np.ndarray
    qdd_a: np.ndarray
    r: np.ndarray


def wrap_error(e: ArrayLike, continuous: ArrayLike) -> np.ndarray:
    """Position error wrapped to (-pi, pi] on continuous joints."""
    e = np.asarray(e, float)
    return np.where(continuous, np.mod(e + np.pi, 2 * np.pi) - np.pi, e)


def tracking_errors(
    Kr: ArrayLike,
    q: ArrayLike,
    v: ArrayLike,
    *,
    q_d: ArrayLike,
    qd_d: ArrayLike,
    qdd_d: ArrayLike,
    continuous: ArrayLike,
) -> TrackingErrors:
    e = wrap_error(np.asarray(q_d, float) - q, continuous)
    edot = np.asarray(qd_d, float) - v
    return TrackingErrors(e, edot, qd_d + Kr * e, qdd_d + Kr * edot, edot + Kr * e)


def disturbance_bound(
    wp: np.ndarray, theta0: ArrayLike, theta_box: Interval
) -> tuple[np.ndarray, Interval, np.ndarray]:
    """(tau_nom, [tau], w_bar): nominal torque, its exact hull over the box, per-joint bound."""
    tau_nom = wp @ theta0
    tau_box = matmul(wp, theta_box)
    w_bar = np.nextafter(np.maximum(tau_box.hi - tau_nom, tau_nom - tau_box.lo), np.inf)
    return tau_nom, tau_box, np.maximum(w_bar, 0.0)


def lyapunov_upper(wm_r: np.ndarray, r: ArrayLike, theta_box: Interval) -> float:
    """V_bar = max over the box of 1/2 r^T M(q; theta) r, with wm_r = Wm(q, r) (exact hull)."""
    row = (np.asarray(r, float) @ wm_r)[None, :]
    return 0.5 * float(matmul(row, theta_box).hi[0])


def spectral_bound(a: ArrayLike) -> np.ndarray | float:
    """Upper bound of max over unit u of u^T a u, i.e. the largest eigenvalue of the symmetric
    part of a (..., n, n). eigvalsh is backward stable (its eigenvalues are those of a + E with
    |E|_2 <= p(n) u |a|_2, p(n) a small multiple of n), so 1e-12 |a|_F covers its error."""
    a = np.asarray(a, float)
    sym = 0.5 * (a + np.swapaxes(a, -1, -2))
    top = np.linalg.eigvalsh(sym)[..., -1]
    return np.nextafter(top + 1e-12 * np.linalg.norm(sym, axis=(-2, -1)), np.inf)


def mass_spread(robot: RobotModel, q: ArrayLike, theta_lo: ArrayLike, *, theta_hi: ArrayLike) -> float:
    """mu(q) = lambda_max(sum_k (hi_k - lo_k) |dM/dtheta_k(q)|) (entrywise |.|), an upper bound of
    max over unit u of sum_k (hi_k - lo_k) |u^T dM/dtheta_k(q) u| (|u^T A u| <= |u|^T |A| |u|): the
    largest change of u^T M u between two parameters of the box, at configuration q (n,). M
    includes the armature (as V does); dM/dtheta_k from the momentum regressor
    (reachability.interval_mass_spread: the same over boxes of configurations)."""
    n = robot.n
    columns = robot.momentum_regressor(np.repeat(np.asarray(q, float)[None], n, 0), np.eye(n))  # [j, i, k]
    widths = np.asarray(theta_hi, float) - theta_lo
    spread = np.einsum("jik,k->ij", np.abs(columns), widths) * (1 + dot_rounding(len(widths)))
    return float(spectral_bound(spread))


def robust_gain_bound(w_bar_norm: ArrayLike, alpha: float, eps: float, *, mu: ArrayLike) -> np.ndarray | float:
    """Upper bound of lambda on the tube (true V <= V_max, so |r| <= eps): |w_bar| + alpha eps mu / 2
    (module docstring; mu from `mass_spread` at q or over a box of configurations)."""
    return np.nextafter(np.asarray(w_bar_norm, float) + 0.5 * alpha * eps * np.asarray(mu, float) * _UP, np.inf)


def robust_input(r: np.ndarray, w_bar: np.ndarray, h: float, *, alpha: float) -> tuple[np.ndarray, float]:
    """(v, lambda): v = lambda r/|r|, lambda = max(0, -alpha h/|r| + |w_bar|)."""
    norm_r = float(np.sqrt(r @ r))
    if norm_r < _TINY_R:
        return np.zeros_like(r), 0.0
    lam = max(0.0, -alpha * h / norm_r + float(np.sqrt(w_bar @ w_bar)) * _UP)
    return lam * r / norm_r, lam


@dataclass
class ArmourOutput:
    u: np.ndarray
    tau_nom: np.ndarray
    v: np.ndarray
    w_bar: np.ndarray
    V_bar: float
    h: float
    lam: float
    err: TrackingErrors


def armour_control(
    dyn: ControllerDynamics,
    gains: ArmourGains,
    q: ArrayLike,
    v: ArrayLike,
    q_d: ArrayLike,
    qd_d: ArrayLike,
    qdd_d: ArrayLike,
    theta0: ArrayLike,
    theta_box: Interval,
) -> ArmourOutput:
    """One evaluation of the ARMOUR law at measured (q, v) and desired (q_d, qd_d, qdd_d)."""
    q, v = np.asarray(q, float), np.asarray(v, float)
    err = tracking_errors(gains.Kr, q, v, q_d=q_d, qd_d=qd_d, qdd_d=qdd_d, continuous=dyn.robot.joint_params.continuous)
    wp, wm_r = dyn.regressors(q, v, err.qd_a, aa=err.qdd_a, x=err.r)
    # [tau] and the hull of r^T M r in one interval product (same as disturbance_bound and
    # lyapunov_upper, which the tests check separately).
    n = len(q)
    hull = matmul(np.vstack([wp, err.r @ wm_r]), theta_box)
    tau_nom = wp @ theta0
    w_bar = np.maximum(np.nextafter(np.maximum(hull.hi[:n] - tau_nom, tau_nom - hull.lo[:n]), np.inf), 0.0)
    V_bar = 0.5 * float(hull.hi[n])
    h = gains.V_max - V_bar
    v_rob, lam = robust_input(err.r, w_bar, h, alpha=gains.alpha)
    return ArmourOutput(tau_nom + v_rob, tau_nom, v_rob, w_bar, V_bar, h, lam, err)


# ---- the ultimate bound ---------------------------------------------------------------------------
def mass_matrix_lower_bound(n: int, theta_lower: ArrayLike) -> float:
    """Certified sigma_min: a lower bound of eig(M(q; theta)) for every q and every physically
    consistent theta whose armature entries are >= those of theta_lower.

    Proof: M(q; theta) = sum_i J_i^T I_i J_i + diag(Ia). Physical consistency (pseudo-inertia
    PSD) makes every spatial inertia I_i PSD, so the rigid part is PSD for every q; by Weyl,
    eig_min(M) >= eig_min(rigid) + min_j Ia_j >= min_j Ia_lower_j. No sampling involved.
    It is also nearly tight: eig_min(M) <= e_j^T M e_j = Ia_j + M_rigid,jj(q) for every j, and
    the rigid diagonal is small next to the Gen3 armature (test_controller shows the gap).
    Boxes containing non-physical theta do not matter: only the TRUE theta (a real body) enters
    the argument V_true <= V_max => |r| <= sqrt(2 V_max / sigma_min).
    """
    theta_lower = np.asarray(theta_lower, float)
    ia = theta_lower[[friction_index(n, j, "Ia") for j in range(n)]]
    return float(np.min(ia))


def ultimate_bound(V_max: float, sigma_min: float) -> float:
    """epsilon with |r|_2 <= epsilon whenever V <= V_max (inf when sigma_min <= 0)."""
    if sigma_min <= 0:
        return np.inf
    return float(np.sqrt(2 * V_max / sigma_min) * _UP)


@dataclass(frozen=True)
class TrackingBounds:
    """Per-joint bounds the planner uses (valid for all t when e(0) = 0 and V(0) <= V_max).

    |r_i| <= eps; r_i = edot_i + Kr_i e_i is a stable first-order filter of e_i, so
        |e_i| <= eps/Kr_i                                        (position)
        |edot_i| = |r_i - Kr_i e_i| <= 2 eps                     (velocity)
        |qd_a,i - qd_d,i| = Kr_i |e_i| <= eps;  |qd_a,i - qd_i| = |r_i| <= eps
        |qdd_a,i - qdd_d,i| = Kr_i |edot_i| <= 2 Kr_i eps.
    With e_i(0) != 0 the position bound is |e_i(0)| e^{-Kr t} + eps/Kr (1 - e^{-Kr t}).
    """

    eps: float
    position: np.ndarray  # |q - q_d|
    velocity: np.ndarray  # |qd - qd_d|
    qd_a: np.ndarray  # |qd_a - qd_d|
    qdd_a: np.ndarray  # |qdd_a - qdd_d|
    alpha: float  # the barrier rate: lambda <= |w_bar| + alpha eps mu / 2 (robust_gain_bound)

    @classmethod
    def from_ultimate_bound(
        cls, V_max: float, sigma_min: float, Kr: ArrayLike, *, n: int, alpha: float
    ) -> TrackingBounds:
        """Bounds of n joints (Kr scalar or per joint) from V_max, sigma_min and the barrier rate."""
        return tracking_bounds(np.broadcast_to(np.asarray(Kr, float), (n,)), V_max, sigma_min, alpha=alpha)

    @classmethod
    def zero(cls, n: int) -> TrackingBounds:
        """Perfect tracking (tests only)."""
        return cls(0.0, np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), 0.0)

    @classmethod
    def coerce(cls, bounds: TrackingBounds | None, n: int) -> TrackingBounds:
        """None -> zero(n); otherwise the same bounds with every field an (n,) array."""
        if bounds is None:
            return cls.zero(n)
        full = lambda x: np.broadcast_to(np.asarray(x, float), (n,)).copy()  # noqa: E731
        return cls(
            float(bounds.eps),
            full(bounds.position),
            full(bounds.velocity),
            full(bounds.qd_a),
            full(bounds.qdd_a),
            float(bounds.alpha),
        )


def tracking_bounds(Kr: ArrayLike, V_max: float, sigma_min: float, *, alpha: float) -> TrackingBounds:
    Kr = np.asarray(Kr, float)
    eps = ultimate_bound(V_max, sigma_min)
    ones = np.ones_like(Kr)
    return TrackingBounds(eps, eps / Kr * _UP, 2 * eps * ones, eps * ones, 2 * Kr * eps * _UP, float(alpha))


def tracking_bounds_for(robot: RobotModel, gains: ArmourGains, theta_lower: ArrayLike) -> TrackingBounds:
    """Convenience: bounds from a RobotModel, the gains and the lower end of [theta]."""
    return tracking_bounds(gains.Kr, gains.V_max, mass_matrix_lower_bound(robot.n, theta_lower), alpha=gains.alpha)
