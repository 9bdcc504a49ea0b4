"""The 1 kHz controller path made cheap: the same ARMOUR law and regressors as systems/controller/armour.py
(tests/test_bench.py checks them equal to 1e-12 on fixed states, and the law's hull against
exact rational arithmetic), compiled for serial chains (systems/controller/armour_kernel.py):
- the bodies' motion transforms are products of the links' 6 x 6 transforms
  Ad(X_pj) diag(Rot, Rot) Ad(X_jc), linear in (1, sin q, 1 - cos q) (Rodrigues): three constant
  terms per link, built here once; joint screws S = Y s, and X^T = Y with blocks swapped;
- the law needs only r^T Wm(q, r), so Wm itself is never formed;
- the box's mid, radius and magnitude (what the interval product needs) and the validity
  check of the theta inputs are computed once per [theta] input, not once per step.
Trees that are not chains fall back to ControllerDynamics' general code.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from safesysid.systems.controller import armour_kernel
from safesysid.systems.controller.armour import _BILINEAR as _BILINEAR_TENSOR
from safesysid.systems.controller.armour import (
    _INERTIA,
    _SKEW,
    _TINY_R,
    _UP,
    ArmourGains,
    ArmourOutput,
    ControllerDynamics,
    TrackingErrors,
    armour_control,
)
from safesysid.systems.math.intervals import Interval, dot_rounding

if TYPE_CHECKING:
    from safesysid.systems.model.robot_model import RobotModel

# The bilinear maps as their nonzeros (armour_kernel.sparse_bilinear): x -> I(x) (6 -> 6 x 10),
# (v, va) -> B(v) va, and x -> x^T I x (K(x)[k, l] = sum_m x_m _INERTIA[m, 10 k + l], so over the
# pairs x_m x_k: 36 -> 10).
_INERTIA_NZ = armour_kernel.sparse_bilinear(_INERTIA, width=1)
_BILINEAR_NZ = armour_kernel.sparse_bilinear(_BILINEAR_TENSOR)
_ENERGY_NZ = armour_kernel.sparse_bilinear(_INERTIA.reshape(36, 10))


def _adjoint(T):
    """Motion-vector transform [w; v] of homogeneous transforms T (..., 4, 4): [[R, 0], [[p]x R, R]]."""
    R, p = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = out[..., 3:, 3:] = R
    out[..., 3:, :3] = (p @ _SKEW).reshape(p.shape[:-1] + (3, 3)) @ R
    return out


class FastControllerDynamics(ControllerDynamics):
    """ControllerDynamics with the serial-chain fast path (same results to rounding)."""

    def __init__(self, robot: RobotModel) -> None:
        super().__init__(robot)
        n = self.n
        # Body i -> its parent as a motion transform: Ad(X_pj Rot(q_i) X_jc) = Ad(X_pj) Ad(Rot) Ad(X_jc),
        # and Ad(Rot) = diag(Rot, Rot) with Rot = I + sin q K + (1 - cos q) K^2 (Rodrigues): linear in
        # (1, sin q, 1 - cos q), so three constant (n, 6, 6) terms give it.
        eye, zero = np.broadcast_to(np.eye(3), (n, 3, 3)), np.zeros((n, 3, 3))
        rot = [np.block([[k, zero], [zero, k]]) for k in (eye, self.k1, self.k2)]
        local = np.stack([_adjoint(self.x_pj) @ r @ _adjoint(self.x_jc) for r in rot], 1)
        # Joint screw in its body's frame (constant: the rotation leaves its axis fixed).
        screw = np.linalg.solve(_adjoint(self.x_jc), np.concatenate([self.axis, np.zeros((n, 3))], 1)[:, :, None])
        # Everything the kernels need besides the sample (armour_kernel.armour_law's `dynamics`).
        self.kernel_constants = (
            np.ascontiguousarray(local),
            np.ascontiguousarray(screw[:, :, 0]),
            np.asarray(self.gravity_acc, float),
            float(self.smoothing),
            _INERTIA_NZ,
            _BILINEAR_NZ,
            _ENERGY_NZ,
        )

    def regressors(
        self, q: ArrayLike, v: ArrayLike, va: ArrayLike, *, aa: ArrayLike, x: ArrayLike
    ) -> tuple[np.ndarray, np.ndarray]:
        if not self.serial:
            return super().regressors(q, v, va, aa=aa, x=x)
        out = armour_kernel.chain_regressors(*_samples(q, v, va, aa, x), self.kernel_constants)
        return out[0], out[1]

    def passivity_and_energy(
        self, q: ArrayLike, v: ArrayLike, va: ArrayLike, *, aa: ArrayLike, r: ArrayLike
    ) -> np.ndarray:
        """(n + 1, 14 n): rows 0..n-1 Wp(q, v, va, aa), row n r^T Wm(q, r) (2 x the kinetic
        energy of r as a function of theta: the body terms r_b^T I r_b, without Wm itself)."""
        if not self.serial:
            wp, wm_r = self.regressors(q, v, va, aa=aa, x=r)
            return np.vstack([wp, np.asarray(r, float).reshape(-1) @ wm_r])
        return armour_kernel.chain_passivity_energy(*_samples(q, v, va, aa, r), self.kernel_constants)


def _samples(*arrays):
    return tuple(np.ascontiguousarray(a, float).reshape(-1) for a in arrays)


class FastArmourLaw:
    """armour.armour_control with the parameter inputs' derived vectors cached between steps.

    law(q, v, q_d, qd_d, qdd_d, theta0, theta_lower, theta_upper) -> ArmourOutput, or None when
    the theta inputs are invalid (not finite, or lower > upper): the caller's fallback.
    """

    def __init__(self, dyn: FastControllerDynamics, gains: ArmourGains) -> None:
        self.dyn, self.gains = dyn, gains
        self.continuous = np.asarray(dyn.robot.joint_params.continuous, bool)
        self._Kr = np.broadcast_to(np.asarray(gains.Kr, float), (dyn.n,)).copy()
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
            box = Interval(lo, hi)
            self._mid_theta0 = np.stack([box.mid, theta0], 1)
            # Per parameter, outward; intervals.matmul's allowance for the float products, here
            # for the kernel's sum of |a| spread, which is itself rounded (dot_rounding).
            self._spread = np.nextafter(box.rad + dot_rounding(len(lo)) * box.mag, np.inf)
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
        g, dyn = self.gains, self.dyn
        if not dyn.serial:  # a tree: the reference law (no robot of this project takes it)
            return armour_control(dyn, g, q, v, q_d, qd_d, qdd_d, theta0, Interval(theta_lower, theta_upper))
        u, tau_nom, v_rob, w_bar, V_bar, h, lam, e, edot, qd_a, qdd_a, r = armour_kernel.armour_law(
            *_samples(q, v, q_d, qd_d, qdd_d),
            self._Kr,
            self.continuous,
            float(g.alpha),
            float(g.V_max),
            self._mid_theta0,
            self._spread,
            _UP,
            _TINY_R,
            dyn.kernel_constants,
        )
        return ArmourOutput(u, tau_nom, v_rob, w_bar, V_bar, h, lam, TrackingErrors(e, edot, qd_a, qdd_a, r))
