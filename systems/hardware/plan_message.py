"""The plan message of the controller-beside-the-arm placement (`arm.control_loop: arm`): pure
conversions between a certified plan and Drake's generic `lcmt_drake_signal` (docs/hardware.md).

A plan is one degree-5 Bézier piece of Algorithm 2 (systems/planner/trajectory_source.py Piece:
it starts at t_start, on the arm's clock, and rests at q_end after its duration: its own brake)
with the parameters it was certified with (θ0, [θ]: the controller's inputs while it executes).
The curve crosses as the parameters that define it, (q0, v0, a0, q_end, T), from which
QuinticBezier.control_points gives its six control points: the same doubles on both sides, so
the arm's continuity check between two plans is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from drake import lcmt_drake_signal
from safesysid.systems.math.bezier import QuinticBezier
from safesysid.systems.planner.trajectory_source import Piece

from .messages import utime_of

_CURVE = ("q0", "v0", "a0", "q_end")
_THETAS = ("theta0", "theta_lower", "theta_upper")


@dataclass(frozen=True)
class Plan:
    piece: Piece  # t_start on the arm's clock
    thetas: tuple[np.ndarray, np.ndarray, np.ndarray]  # θ0, lower, upper it was certified with


def plan_message(plan: Plan, *, sent_s: float) -> lcmt_drake_signal:
    """The plan as an lcmt_drake_signal (timestamp: the sender's clock at sending [µs])."""
    piece, n = plan.piece, len(plan.piece.q_end)
    curve = piece.curve
    parts = [[piece.t_start, curve.duration], curve.q0, curve.v0, curve.a0, piece.q_end, *plan.thetas]
    values = np.concatenate([np.asarray(p, float).ravel() for p in parts])
    p = len(plan.thetas[0])
    msg = lcmt_drake_signal()
    msg.val = [float(x) for x in values]
    msg.coord = (
        ["t_start_s", "duration_s"]
        + [f"{name}_{k + 1}" for name in _CURVE for k in range(n)]
        + [f"{name}_{k + 1}" for name in _THETAS for k in range(p)]
    )
    msg.dim = len(msg.val)
    msg.timestamp = utime_of(sent_s)
    return msg


def parse_plan(msg: lcmt_drake_signal, n: int) -> Plan | None:
    """The plan of an n-joint arm, or None when the message is not one (its size, a non-finite
    value, a non-positive duration or an empty box)."""
    values = np.asarray(msg.val, float)
    p, rest = divmod(len(values) - 2 - 4 * n, 3)
    if msg.dim != len(values) or rest or p < 1 or not np.all(np.isfinite(values)) or values[1] <= 0:
        return None
    q0, v0, a0, q_end = values[2 : 2 + 4 * n].reshape(4, n)
    theta0, lower, upper = values[2 + 4 * n :].reshape(3, p)
    if np.any(lower > upper):
        return None
    curve = QuinticBezier(q0.copy(), v0.copy(), a0.copy(), float(values[1]))
    return Plan(Piece(float(values[0]), curve, q_end.copy()), (theta0.copy(), lower.copy(), upper.copy()))
