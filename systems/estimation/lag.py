"""The torque a lagged sensor read, recovered exactly (estimator.torque_lag_s).

Sensor model (the simulated arm's `TorqueSensor`, and a torque sensor that low-passes its own
reading): the raw reading r_k = τ_k + w_k of the torque held over [t_k, t_k+1] (w inside the
declared bound) passes a first-order lag d y' + y = r, so the logged samples obey
    y_k+1 = a_k y_k + (1 − a_k) r_k,   a_k = exp(−h_k / d),   h_k = t_k+1 − t_k,
exactly (r is constant over the step). Hence r_k = y_k + (y_k+1 − y_k) / (1 − a_k): the reading
of step k is known once sample k+1 has arrived, and with it the declared bound holds for r_k as
it does for an unlagged sensor, so everything downstream (∫τ, the radii, the LP) is unchanged.
A noise added AFTER the filter would be amplified ~2d/h by this inversion; the offline
`safesysid sysid --model` path (app/sysid_cli.py undo_torque_lag) bounds that case instead.

A lag declared as an interval [lo, hi] (a diagnosed lag is an estimate): r_k(d) = y_k + Δy_k g_k(d)
with g_k(d) = 1/(1 − exp(−h_k/d)) increasing in d, so over d ∈ [lo, hi] the reading lies between
r_k(lo) and r_k(hi). `unlag_interval` publishes their midpoint c_k and a radius ρ_k ≥ |r_k(d) − c_k|
for every d in the interval (with the float rounding of both inversions, `inversion_rounding`);
segments.torque_radius adds ρ_k to the row's noise budget. One value (lo == hi) is the exact
inversion, ρ = 0.

Float rounding of the (one-value) inversion (~eps·|y|·2/(1 − a): 2.4e-12 N·m at |y| = 50 N·m, d = 0.11 s,
h = 1 ms) is inside the relative pads of the hull (64 eps per row on |L||U|) and of the LP
(1e-9 of each row's bound, ≥ 5e-11 N·m per sample) in enclosure.py.
"""

from __future__ import annotations

import numpy as np

from .settings import EPS, EstimatorError, lag_interval


def unlag(t: np.ndarray, y: np.ndarray, lag_s: float) -> np.ndarray:
    """(N − 1, n) readings r_k of the steps [t_k, t_k+1] from N lagged samples y (N, n)."""
    h = np.diff(t)
    keep = np.exp(-h / lag_s)
    return y[:-1] + np.diff(y, axis=0) / (1.0 - keep)[:, None]


def inversion_rounding(t: np.ndarray, y: np.ndarray, lag_s: float) -> np.ndarray:
    """(N − 1, n) bound on |float(unlag) − unlag| at lag_s: exp and the division err by ≤ eps,
    1 − a by ≤ 3 eps g relative (a within eps of its value), Δy and the sum by eps, so to first
    order ≤ 4 eps (|y_k| + |Δy_k| g (g + 1)), g = 1/(1 − a) ≥ 1."""
    g = 1.0 / (1.0 - np.exp(-np.diff(t) / lag_s)) if lag_s > 0 else np.ones(len(t) - 1)
    return 4 * EPS * (np.abs(y[:-1]) + np.abs(np.diff(y, axis=0)) * (g * (g + 1))[:, None])


def unlag_interval(t: np.ndarray, y: np.ndarray, lo: float, *, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """(centre c, radius ρ) of the readings of the steps, (N − 1, n) each: |r_k(d) − c_k| ≤ ρ_k for
    every lag d in [lo, hi] (r_k monotone in d: its ends r_k(lo), r_k(hi) bound it). lo == hi:
    `unlag` and ρ = 0 (the exact inversion, its rounding inside the estimator's pads)."""
    if lo == hi:
        return unlag(t, y, lo), np.zeros((len(t) - 1, y.shape[1]))
    ends = [unlag(t, y, d) if d > 0 else y[1:] for d in (lo, hi)]  # d → 0: the reading is y_k+1
    centre = 0.5 * (ends[0] + ends[1])
    # rounding: each end's inversion, once in the centre and once in the spread (≤ 2× hi's bound),
    # and that of the midpoint and of the half-difference
    spread = (
        0.5 * np.abs(ends[1] - ends[0]) + 2 * inversion_rounding(t, y, hi) + EPS * (np.abs(ends[0]) + np.abs(ends[1]))
    )
    return centre, spread * (1 + 4 * EPS)


class LagInverse:
    """Streams samples (t, q, v, y) into (t, q, v, r) one sample late: each chunk's last sample
    waits for its successor. A sample whose next step is longer than `max_step_s` (samples were
    lost: the readings over that span are unknown) is dropped; the estimator's segments never
    span the gap that leaves."""

    def __init__(self, lag_s: float | tuple[float, float], max_step_s: float) -> None:
        self.lo, self.hi = lag_interval(lag_s)
        self.max_step_s = float(max_step_s)
        self._tail = None  # (t, q, v, y) of the last sample, waiting for the next

    def push(
        self, t: np.ndarray, q: np.ndarray, v: np.ndarray, *, y: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The samples whose reading is now known, (t, q, v, r, ρ); y the lagged torque, r the
        reading (the centre over a lag interval), ρ its radius over the interval (0 for one lag)."""
        if self._tail is not None:
            t, q, v, y = (np.concatenate([[a], b]) for a, b in zip(self._tail, (t, q, v, y)))
        if len(t) == 0:
            return t, q, v, y, y.copy()
        if np.any(np.diff(t) <= 0):
            raise EstimatorError("time is not strictly increasing")
        self._tail = (t[-1], q[-1], v[-1], y[-1])
        step_ok = np.diff(t) <= self.max_step_s
        r, rho = unlag_interval(t, y, self.lo, hi=self.hi)
        return t[:-1][step_ok], q[:-1][step_ok], v[:-1][step_ok], r[step_ok], rho[step_ok]
