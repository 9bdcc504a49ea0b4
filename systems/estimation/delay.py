"""The torque of each step from a log whose torque is shifted in time (estimator.torque_delay_s).

A late reading (s > 0: the sensor's reading of the torque held over [t_k, t_k+1] is logged at
t_k + s, the simulated arm's `torque_sensor_delay_s`) or a late torque (s < 0: the joint receives
at t_k the motor torque the sensor read at t_k − |s|, its `time_delay_s`) pairs each motion step
with the sample |s| away. Both are whole steps in the simulated arm (systems/plant/station.py
StepDelay, exact: tests/test_plant_friction.py), so re-pairing them is exact and the declared
noise bound holds for the re-paired reading as for an immediate one: everything downstream (∫τ,
the radii, the LP) is unchanged. A step whose reading never arrives (lost, or before the log's
first sample) is dropped; the estimator's segments never span the gap that leaves.
"""

from __future__ import annotations

import numpy as np

from .settings import EstimatorError


class DelayInverse:
    """Streams samples (t, q, v, y) into (t, q, v, τ): step k's τ is the sample within half a
    hold period of t_k + shift_s. A step waits until its reading has arrived or cannot arrive
    any more (a later sample is past it)."""

    def __init__(self, shift_s: float, hold_s: float) -> None:
        self.shift_s, self.half = float(shift_s), 0.5 * float(hold_s)
        self._motion = None  # (t, q, v) of the steps waiting for their reading
        self._readings = None  # (t, y) a waiting or a future step can still pair with

    def push(
        self, t: np.ndarray, q: np.ndarray, v: np.ndarray, *, y: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The steps whose reading is now known, (t, q, v, τ); y the logged torque."""
        motion, readings = (t, q, v), (t, y)
        if self._motion is not None:
            motion = tuple(np.concatenate([a, b]) for a, b in zip(self._motion, motion))
            readings = tuple(np.concatenate([a, b]) for a, b in zip(self._readings, readings))
        t_m, t_r = motion[0], readings[0]
        if len(t_r) == 0:
            return t, q, v, y
        if np.any(np.diff(t_m) <= 0) or np.any(np.diff(t_r) <= 0):
            raise EstimatorError("time is not strictly increasing")
        target = t_m + self.shift_s
        j = np.searchsorted(t_r, target - self.half)
        found = j < len(t_r)
        found[found] = t_r[j[found]] < target[found] + self.half
        decided = found | (t_r[-1] >= target + self.half)  # else its reading may still arrive
        self._motion = tuple(x[~decided] for x in motion)
        oldest = min(target[~decided].min(initial=np.inf), t_r[-1] + self.shift_s) - self.half
        self._readings = tuple(x[t_r >= oldest] for x in readings)
        use = decided & found
        return t_m[use], motion[1][use], motion[2][use], readings[1][j[use]]
