"""The plan message of the controller-beside-the-arm placement (`arm.control_loop: arm`): pure
conversions between a certified plan and Drake's generic `lcmt_drake_signal` (docs/hardware.md).

A plan is one degree-5 Bézier piece of Algorithm 2 (systems/planner/trajectory_source.py Piece:
it starts at t_start, on the arm's clock, and rests at q_end after its duration: its own brake)
or one curve of the task phase (TimedCurve: a rest-to-rest PiecewiseBezier, the return move or
the task trajectory; the last one carries `release`: the payload is let go at its end), with the
parameters it was certified with (θ0, [θ]: the controller's inputs while it executes).
A Bézier piece crosses as the parameters that define it, (q0, v0, a0, q_end, T), from which
QuinticBezier.control_points gives its six control points; a task curve as its control points
and piece duration: the same doubles on both sides, so the arm's continuity check between two
plans is exact up to the evaluation's rounding. The second coordinate's name tells the two apart
(`duration_s` or `piece_duration_s`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from drake import lcmt_drake_signal
from safesysid.systems.math.bezier import QuinticBezier
from safesysid.systems.math.piecewise_bezier import PiecewiseBezier
from safesysid.systems.planner.trajectory_source import Piece, TimedCurve

from .messages import utime_of

_CURVE = ("q0", "v0", "a0", "q_end")
_THETAS = ("theta0", "theta_lower", "theta_upper")
REST_TOLERANCE = 1e-6  # a task curve's velocity and acceleration at its end [rad/s, rad/s²]


@dataclass(frozen=True)
class Plan:
    piece: Piece | TimedCurve  # t_start on the arm's clock
    thetas: tuple[np.ndarray, np.ndarray, np.ndarray]  # θ0, lower, upper it was certified with
    release: bool = False  # the payload is released at its end (the task trajectory's last curve)


def plan_message(plan: Plan, *, sent_s: float) -> lcmt_drake_signal:
    """The plan as an lcmt_drake_signal (timestamp: the sender's clock at sending [µs])."""
    names, parts = _task_curve_fields(plan) if isinstance(plan.piece, TimedCurve) else _piece_fields(plan.piece)
    p = len(plan.thetas[0])
    msg = lcmt_drake_signal()
    msg.val = [float(x) for x in np.concatenate([np.asarray(v, float).ravel() for v in [*parts, *plan.thetas]])]
    msg.coord = names + [f"{name}_{k + 1}" for name in _THETAS for k in range(p)]
    msg.dim = len(msg.val)
    msg.timestamp = utime_of(sent_s)
    return msg


def _piece_fields(piece: Piece) -> tuple[list[str], list]:
    curve, n = piece.curve, len(piece.q_end)
    names = ["t_start_s", "duration_s"] + [f"{name}_{k + 1}" for name in _CURVE for k in range(n)]
    return names, [[piece.t_start, curve.duration], curve.q0, curve.v0, curve.a0, piece.q_end]


def _task_curve_fields(plan: Plan) -> tuple[list[str], list]:
    curve = plan.piece.curve
    num_pieces, _, n = curve.control_points.shape
    names = ["t_start_s", "piece_duration_s", "num_pieces", "release"]
    names += [f"p{j + 1}_c{c}_q{k + 1}" for j in range(num_pieces) for c in range(6) for k in range(n)]
    head = [plan.piece.t_start, curve.piece_duration, num_pieces, float(plan.release)]
    return names, [head, curve.control_points]


def parse_plan(msg: lcmt_drake_signal, n: int) -> Plan | None:
    """The plan of an n-joint arm, or None when the message is not one (its size, a non-finite
    value, a non-positive duration, an empty box, a task curve not at rest at its end)."""
    values = np.asarray(msg.val, float)
    if msg.dim != len(values) or len(values) < 4 or not np.all(np.isfinite(values)) or values[1] <= 0:
        return None
    task = len(msg.coord) > 1 and msg.coord[1] == "piece_duration_s"
    parsed = _parse_task_curve(values, n) if task else _parse_piece(values, n)
    if parsed is None:
        return None
    piece, rest, release = parsed
    p, extra = divmod(len(rest), 3)
    if extra or p < 1:
        return None
    theta0, lower, upper = rest.reshape(3, p).copy()
    if np.any(lower > upper):
        return None
    return Plan(piece, (theta0, lower, upper), release)


def _parse_piece(values: np.ndarray, n: int) -> tuple | None:
    q0, v0, a0, q_end = values[2 : 2 + 4 * n].reshape(4, n).copy()
    curve = QuinticBezier(q0, v0, a0, float(values[1]))
    return Piece(float(values[0]), curve, q_end), values[2 + 4 * n :], False


def _parse_task_curve(values: np.ndarray, n: int) -> tuple | None:
    num_pieces, size = values[2], values[2] * 6 * n
    if num_pieces < 1 or num_pieces != int(num_pieces) or values[3] not in (0.0, 1.0) or len(values) < 4 + size:
        return None
    points = values[4 : 4 + int(size)].reshape(int(num_pieces), 6, n).copy()
    curve = PiecewiseBezier(points, float(values[1]))
    _, v, a = curve.evaluate_at(curve.duration)  # the arm parses every repeat: the 1 kHz loop's path
    if max(np.abs(v).max(), np.abs(a).max()) > REST_TOLERANCE:
        return None  # the arm rests at a plan's end: a curve that does not would jump there
    return TimedCurve(float(values[0]), curve), values[4 + int(size) :], bool(values[3])
