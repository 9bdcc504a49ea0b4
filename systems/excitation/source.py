"""FourierSource: the Drake LeafSystem around systems/excitation/fourier.py (kept out of the pure
module, and out of systems/methods.py, which the scenario schema imports without Drake)."""

from __future__ import annotations

import numpy as np
from pydrake.systems.framework import BasicVector, LeafSystem


class FourierSource(LeafSystem):
    """Output 'desired' (3 n) = [q_d, qd_d, qdd_d] of a FourierTrajectory (at rest at q0 outside
    its period)."""

    def __init__(self, trajectory):
        super().__init__()
        self.trajectory = trajectory
        n = len(trajectory.q0)
        self.DeclareVectorOutputPort("desired", BasicVector(3 * n), self._calc, {self.time_ticket()})

    def _calc(self, context, output):
        output.SetFromVector(np.concatenate(self.trajectory.evaluate(context.get_time())))
