"""A joint log: sampled time, joint positions, velocities, measured torques and optional
accelerations of an n-joint arm (the data the diagnosis and the estimator read). The CSV and
ROS bag readers, with their file/field error messages, are in app/ (joint_log.py, joint_bag.py)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class JointLog:
    t: np.ndarray  # (N,) s, strictly increasing
    q: np.ndarray  # (N, n) rad
    v: np.ndarray  # (N, n) rad/s
    tau: np.ndarray  # (N, n) N m, measured
    a: np.ndarray | None = None  # (N, n) rad/s^2 when logged
    extra: dict[str, np.ndarray] = field(default_factory=dict)  # other columns by name
    source: str = ""

    @property
    def n(self) -> int:
        return self.q.shape[1]

    def __len__(self) -> int:
        return len(self.t)

    def slice(self, sl: slice | np.ndarray) -> JointLog:
        """The samples `sl` (a slice, index array or boolean mask) of every column."""
        pick = lambda x: None if x is None else x[sl]  # noqa: E731
        return JointLog(
            self.t[sl],
            self.q[sl],
            self.v[sl],
            self.tau[sl],
            pick(self.a),
            {k: x[sl] for k, x in self.extra.items()},
            self.source,
        )
