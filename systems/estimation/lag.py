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

Float rounding of the inversion (~eps·|y|·2/(1 − a): 2.4e-12 N·m at |y| = 50 N·m, d = 0.11 s,
h = 1 ms) is inside the relative pads of the hull (64 eps per row on |L||U|) and of the LP
(1e-9 of each row's bound, ≥ 5e-11 N·m per sample) in enclosure.py.
"""

from __future__ import annotations

import numpy as np

from .settings import EstimatorError


def unlag(t: np.ndarray, y: np.ndarray, lag_s: float) -> np.ndarray:
    """(N − 1, n) readings r_k of the steps [t_k, t_k+1] from N lagged samples y (N, n)."""
    h = np.diff(t)
    keep = np.exp(-h / lag_s)
    return y[:-1] + np.diff(y, axis=0) / (1.0 - keep)[:, None]


class LagInverse:
    """Streams samples (t, q, v, y) into (t, q, v, r) one sample late: each chunk's last sample
    waits for its successor. A sample whose next step is longer than `max_step_s` (samples were
    lost: the readings over that span are unknown) is dropped; the estimator's segments never
    span the gap that leaves."""

    def __init__(self, lag_s: float, max_step_s: float) -> None:
        self.lag_s = float(lag_s)
        self.max_step_s = float(max_step_s)
        self._tail = None  # (t, q, v, y) of the last sample, waiting for the next

    def push(
        self, t: np.ndarray, q: np.ndarray, v: np.ndarray, y: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The samples whose reading is now known, (t, q, v, r); y the lagged torque."""
        if self._tail is not None:
            t, q, v, y = (np.concatenate([[a], b]) for a, b in zip(self._tail, (t, q, v, y)))
        if len(t) == 0:
            return t, q, v, y
        if np.any(np.diff(t) <= 0):
            raise EstimatorError("time is not strictly increasing")
        self._tail = (t[-1], q[-1], v[-1], y[-1])
        step_ok = np.diff(t) <= self.max_step_s
        r = unlag(t, y, self.lag_s)[step_ok]
        return t[:-1][step_ok], q[:-1][step_ok], v[:-1][step_ok], r
