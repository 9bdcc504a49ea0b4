"""The 1 kHz controller path made cheap: the same ARMOUR law and regressors as systems/armour.py
(tests/test_bench.py checks them equal to 1e-12 on fixed states), with fewer numpy calls.

At one sample the cost is numpy call overhead, not arithmetic, so for serial chains:
- the bodies' motion transforms are prefix products (log2(n) batched steps) of the links' 6 x 6
  transforms Ad(X_pj) diag(Rot, Rot) Ad(X_jc), linear in (1, sin q, 1 - cos q) (Rodrigues), so
  one product with three constant terms; joint screws S = Y s, and X^T = Y with blocks swapped;
- the tree sums of the twists of v, va, x and of S aa are one product; dS/dt va the bilinear
  cross of (V_parent, S va);
- per body, [I a + B(v) va, r^T I r] is one product, so Wm itself is never formed (the law
  needs only r^T Wm(q, r));
- the box's mid, radius and magnitude (what the interval product needs) and the validity
  check of the theta inputs are computed once per [theta] input, not once per step.
Trees that are not chains fall back to ControllerDynamics' general code.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from . import regressors
from .armour import (
    _BILINEAR,
    _CROSS_MOTION,
    _INERTIA,
    _SKEW,
    _TINY_R,
    _UP,
    ArmourGains,
    ArmourOutput,
    ControllerDynamics,
    TrackingErrors,
    _outer,
    wrap_error,
)

if TYPE_CHECKING:
    from .robot_model import RobotModel

# x^T K(x): K(x)[k, l] = sum_m x_m _INERTIA[m, 10 k + l], so over the outer product x_m x_k (36 x 10).
_ENERGY = _INERTIA.reshape(36, 10)
# [a, v (x) va, r (x) r] (78) -> [I a + B(v) va (60), r^T I r (10)]: block diagonal in the two outputs.
_PASSIVITY_ENERGY = np.zeros((78, 70))
_PASSIVITY_ENERGY[:42, :60] = np.vstack([_INERTIA, _BILINEAR])
_PASSIVITY_ENERGY[42:, 60:] = _ENERGY
_ROUNDING = 4 * np.finfo(float).eps  # intervals.matmul's allowance for the float products


def _adjoint(T):
    """Motion-vector transform [w; v] of homogeneous transforms T (..., 4, 4): [[R, 0], [[p]x R, R]]."""
    R, p = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = out[..., 3:, 3:] = R
    out[..., 3:, :3] = (p @ _SKEW).reshape(p.shape[:-1] + (3, 3)) @ R
    return out


class FastControllerDynamics(ControllerDynamics):
    """ControllerDynamics with the serial-chain fast path (same results to rounding). It keeps
    scratch buffers between calls, so one instance must not be shared between threads (the
    project runs in parallel with processes only)."""

    def __init__(self, robot: RobotModel) -> None:
        super().__init__(robot)
        n = self.n
        # Body i -> its parent as a motion transform: Ad(X_pj Rot(q_i) X_jc) = Ad(X_pj) Ad(Rot) Ad(X_jc),
        # and Ad(Rot) = diag(Rot, Rot) with Rot = I + sin q K + (1 - cos q) K^2 (Rodrigues): linear in
        # (1, sin q, 1 - cos q), so one product with three constant (n, 6, 6) terms gives it.
        eye, zero = np.broadcast_to(np.eye(3), (n, 3, 3)), np.zeros((n, 3, 3))
        rot = [np.block([[k, zero], [zero, k]]) for k in (eye, self.k1, self.k2)]
        self._local = np.stack([_adjoint(self.x_pj) @ r @ _adjoint(self.x_jc) for r in rot], 1).reshape(n, 3, 36)
        self._weights = np.ones((n, 1, 3))
        # Joint screw in its body's frame (constant: the rotation leaves its axis fixed).
        screw = np.concatenate([self.axis, np.zeros((n, 3))], 1)[:, :, None]
        self._screw = np.linalg.solve(_adjoint(self.x_jc), screw)
        self._Y = np.empty((n + 1, 6, 6))  # [0] the base, [i + 1] body i -> world (motion vectors)
        self._Y[0] = np.eye(6)
        self._prefix_shifts = [1 << k for k in range(max(n - 1, 0).bit_length())]
        # X_i^T = (Y_i^-1)^T is Y_i with its 3 x 3 blocks swapped ([[R, 0], [P R, R]] -> [[R, P R], [0, R]]).
        swap = np.r_[3:6, 0:3]
        self._swap = (swap[:, None], swap[None, :])
        self._v_par = np.zeros((n, 6))
        self._rates = np.empty((n, 4, 1))  # v, va, x, aa per joint
        self._world = np.empty((n, 4 + n, 6))
        p = 14 * n
        j = np.arange(n)
        f0 = 10 * n + 4 * j
        # Flat indices in the (2, n, 14 n) output of [coulomb, va, aa, 1] (Wp) and x (Wm, armature).
        self._friction_at = np.concatenate([j * p + f0 + k for k in range(4)] + [n * p + j * p + f0 + 2])
        self._ones = np.ones(n)
        self._features = np.empty((n, 78))  # per body: a_b, v_b (x) va_b, r_b (x) r_b

    def _transforms(self, q):
        """(S, XT): joint screws in the world (n, 6) and X_i^T (world -> body i, transposed) for a chain."""
        n = self.n
        w = self._weights
        np.sin(q, out=w[:, 0, 1])
        np.subtract(1.0, np.cos(q), out=w[:, 0, 2])
        Y = self._Y
        Y[1:] = (w @ self._local).reshape(n, 6, 6)
        for shift in self._prefix_shifts:  # Y_i = L_0 ... L_i as log2(n) batched products
            Y[1 + shift :] = Y[1:-shift] @ Y[1 + shift :]
        S = (Y[1:] @ self._screw)[:, :, 0]
        return S, Y[1:][:, self._swap[0], self._swap[1]]

    def _body_terms(self, q, v, va, aa, x):
        """(body, s_body): body [i] rows = twists of v, va, x, the acceleration term, all in body
        i; s_body [i, j] = X_i S_j (0 when joint j does not move body i): what both regressors are
        built from. Motion vectors
        are rows here, so one product (rows) @ X_i^T moves all of them to body i."""
        n = self.n
        S, XT = self._transforms(q)
        world = self._world  # [i] rows: V, va twist, x twist, acceleration, S_0 .. S_n-1
        # Twists of v, va and x: [i] = sum over ancestors j of i of S_j x_j (one product for all three).
        rates = self._rates
        rates[:, 0, 0], rates[:, 1, 0], rates[:, 2, 0], rates[:, 3, 0] = v, va, x, aa
        joint = S[:, None, :] * rates  # S_j v_j, S_j va_j, S_j x_j, S_j aa_j
        # Tree sums of all four (ancestors j of i) in one product: the twists of v, va and x, and
        # the S aa part of the acceleration.
        world[:, :4] = (self.anc_t @ joint.reshape(n, 24)).reshape(n, 4, 6)
        v_par = self._v_par
        v_par[1:] = world[:-1, 0]
        # dS_j/dt va_j = V_parent(j) x (S_j va_j); plus gravity (base acceleration).
        world[:, 3] += self.gravity_acc + self.anc_t @ (_outer(v_par, joint[:, 1]) @ _CROSS_MOTION)
        world[:, 4:] = S
        body = world @ XT  # rows as world's, in body i
        return body, body[:, 4:] * self.anc_t[:, :, None]

    def _rigid_columns(self, out, s_body, y):
        """out[..., j, 10 i + l] = (X_i S_j) . y[..., i, :, l] (the joint torques of body i's regressor)."""
        n = self.n
        np.matmul(s_body, y.reshape(-1, n, 6, 10), out=out[..., : 10 * n].reshape(-1, n, n, 10).swapaxes(-3, -2))
        out[..., 10 * n :] = 0.0

    def regressors(
        self, q: ArrayLike, v: ArrayLike, va: ArrayLike, aa: ArrayLike, x: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray]:
        if not self.serial:
            return super().regressors(q, v, va, aa, x)
        q, v, va, aa, x = (np.asarray(a, float).reshape(-1) for a in (q, v, va, aa, x))
        n = self.n
        body, s_body = self._body_terms(q, v, va, aa, x)
        y = np.concatenate([body[:, 3], body[:, 2]]) @ _INERTIA  # I a and I x
        y[:n] += _outer(body[:, 0], body[:, 1]) @ _BILINEAR
        out = np.empty((2, n, 14 * n))
        self._rigid_columns(out, s_body, y)
        coulomb = regressors.coulomb_shape(va, self.smoothing)
        out.reshape(-1)[self._friction_at] = np.concatenate([coulomb, va, aa, self._ones, x])
        return out[0], out[1]

    def passivity_and_energy(
        self, q: ArrayLike, v: ArrayLike, va: ArrayLike, aa: ArrayLike, r: ArrayLike
    ) -> np.ndarray:
        """(n + 1, 14 n): rows 0..n-1 Wp(q, v, va, aa), row n r^T Wm(q, r) (2 x the kinetic
        energy of r as a function of theta: the body terms r_b^T I r_b, without Wm itself)."""
        q, v, va, aa, r = (np.asarray(a, float).reshape(-1) for a in (q, v, va, aa, r))
        if not self.serial:
            wp, wm_r = self.regressors(q, v, va, aa, r)
            return np.vstack([wp, r @ wm_r])
        return self._passivity_and_energy(q, v, va, aa, r)

    def _passivity_and_energy(self, q, v, va, aa, r):
        """passivity_and_energy for a chain, inputs already (n,) float arrays."""
        n = self.n
        body, s_body = self._body_terms(q, v, va, aa, r)
        # Per body [a_b, v_b (x) va_b, r_b (x) r_b] -> [I a + B(v) va, r_b^T I r_b] in one product
        # (body rows: 0 v, 1 va, 2 r, 3 a; the outer products of rows (0, 1) and (2, 2)).
        features = self._features
        features[:, :6] = body[:, 3]
        np.multiply(body[:, 0:3:2, :, None], body[:, 1:3, None, :], out=features[:, 6:].reshape(n, 2, 6, 6))
        y = features @ _PASSIVITY_ENERGY
        out = np.zeros((n + 1, 14 * n))
        np.matmul(s_body, y[:, :60].reshape(n, 6, 10), out=out[:n, : 10 * n].reshape(n, n, 10).swapaxes(0, 1))
        out[n, : 10 * n] = y[:, 60:].reshape(-1)
        out[n, 10 * n + 2 :: 4] = r * r  # armature
        coulomb = np.tanh(va / self.smoothing) if self.smoothing > 0 else np.sign(va)  # regressors.coulomb_shape
        out.reshape(-1)[self._friction_at[: 4 * n]] = np.concatenate([coulomb, va, aa, self._ones])
        return out


class FastArmourLaw:
    """armour.armour_control with the parameter inputs' derived vectors cached between steps.

    law(q, v, q_d, qd_d, qdd_d, theta0, theta_lower, theta_upper) -> ArmourOutput, or None when
    the theta inputs are invalid (not finite, or lower > upper): the caller's fallback.
    """

    def __init__(self, dyn: FastControllerDynamics, gains: ArmourGains) -> None:
        self.dyn, self.gains = dyn, gains
        self.continuous = dyn.robot.joint_params.continuous
        self._key = None  # the bytes of (theta0, lo, hi) the cache below belongs to
        self._valid = False

    def _box(self, theta0, lo, hi):
        """Validity of the theta inputs; caches mid, radius and magnitude of the box (as
        intervals.Interval defines them) and theta0, recomputed only when an input changes."""
        key = b"".join(np.ascontiguousarray(a, float).tobytes() for a in (theta0, lo, hi))
        if key == self._key:
            return self._valid
        self._key = key
        theta0, lo, hi = (np.array(a, float) for a in (theta0, lo, hi))
        self._valid = bool(np.all(np.isfinite(theta0)) and np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)))
        self._valid = self._valid and bool(np.all(lo <= hi))
        if self._valid:
            self._mid_theta0 = np.stack([0.5 * (lo + hi), theta0], 1)
            rad, mag = np.nextafter(0.5 * (hi - lo), np.inf), np.maximum(np.abs(lo), np.abs(hi))
            self._spread = np.nextafter(rad + _ROUNDING * mag, np.inf)  # per parameter, outward
        return self._valid

    def __call__(
        self,
        q: ArrayLike,
        v: ArrayLike,
        q_d: ArrayLike,
        qd_d: ArrayLike,
        qdd_d: ArrayLike,
        theta0: ArrayLike,
        theta_lower: ArrayLike,
        theta_upper: ArrayLike,
    ) -> ArmourOutput | None:
        if not self._box(theta0, theta_lower, theta_upper):
            return None
        g = self.gains
        q, v = np.asarray(q, float), np.asarray(v, float)
        e = wrap_error(np.asarray(q_d, float) - q, self.continuous)
        edot = np.asarray(qd_d, float) - v
        ke = g.Kr * e
        r = edot + ke
        err = TrackingErrors(e, edot, qd_d + ke, qdd_d + g.Kr * edot, r)
        # intervals.matmul([Wp; r^T Wm(q, r)], box): mid +- (rad + rounding allowance), outward.
        dyn = self.dyn
        evaluate = dyn._passivity_and_energy if dyn.serial else dyn.passivity_and_energy
        a = evaluate(q, v, err.qd_a, err.qdd_a, r)  # (n + 1, 14 n)
        n = len(q)
        mid, tau_nom = (a @ self._mid_theta0).T  # box centre and theta0 in one product
        tau_nom = tau_nom[:n]
        spread = np.abs(a) @ self._spread
        lo, hi = np.nextafter(mid - spread, -np.inf), np.nextafter(mid + spread, np.inf)
        w_bar = np.maximum(np.nextafter(np.maximum(hi[:n] - tau_nom, tau_nom - lo[:n]), np.inf), 0.0)
        V_bar = 0.5 * float(hi[n])
        h = g.V_max - V_bar
        v_rob, lam = _robust_input(r, w_bar, h, g.alpha)
        return ArmourOutput(tau_nom + v_rob, tau_nom, v_rob, w_bar, V_bar, h, lam, err)


def _robust_input(r, w_bar, h, alpha):
    """armour.robust_input with scalar math (math.sqrt and np.sqrt are both correctly rounded)."""
    norm_r = math.sqrt(float(r @ r))
    if norm_r < _TINY_R:
        return np.zeros_like(r), 0.0
    lam = max(0.0, -alpha * h / norm_r + math.sqrt(float(w_bar @ w_bar)) * _UP)
    return lam * r / norm_r, lam
