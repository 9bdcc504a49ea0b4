"""Further candidate effects tested outside the library on the residual a diagnosis leaves:
each joint's residual regressed on harmonics of its own angle, fitted on the fit logs and scored
once on the check logs.

  gear_ripple            a_k sin(k q_j) + b_k cos(k q_j), k = 1..HARMONICS: a torque periodic in
                         the joint angle (gear and motor cogging ripple; for a harmonic drive one
                         period per output revolution plus its harmonics)
  position_friction      sgn(v_j) (a_k sin(k q_j) + b_k cos(k q_j)): Coulomb friction varying with
                         the angle (eccentric or unevenly worn gears, cable drag)

Rows are the diagnosis' residual rows (momentum windows are read at their middle sample).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .design import Design, rms

CANDIDATES = ("gear_ripple", "position_friction")
HARMONICS = 2


def candidate_columns(design: Design, joint: int, kind: str) -> np.ndarray:
    """(rows, 2 HARMONICS) columns of a candidate on one joint."""
    q = design.features["q"][:, joint]
    cols = np.column_stack([f(k * q) for k in range(1, HARMONICS + 1) for f in (np.sin, np.cos)])
    if kind == "position_friction":
        cols = cols * np.sign(design.features["v"][:, joint])[:, None]
    elif kind != "gear_ripple":
        raise ValueError(kind)
    return cols


def candidate_gain(
    fit: Sequence[tuple[Design, np.ndarray]], check: Sequence[tuple[Design, np.ndarray]], kind: str
) -> dict:
    """Held-out RMS of the residual left before/after a candidate (per joint and overall): fitted
    by least squares per joint on the unsaturated rows of the (design, residual) pairs of `fit`,
    applied to `check`."""
    n = fit[0][1].shape[1]
    before, after = [], []
    for j in range(n):
        A = np.concatenate([candidate_columns(d, j, kind)[~d.row_saturated[:, j]] for d, _ in fit])
        y = np.concatenate([r[~d.row_saturated[:, j], j] for d, r in fit])
        p = np.linalg.lstsq(A, y, rcond=None)[0]
        before.append(np.concatenate([r[:, j] for _, r in check]))
        after.append(np.concatenate([r[:, j] - candidate_columns(d, j, kind) @ p for d, r in check]))
    b, a = np.column_stack(before), np.column_stack(after)
    return {
        "kind": kind,
        "rms_before": rms(b),
        "rms_after": rms(a),
        "rms_before_per_joint": [rms(b[:, j]) for j in range(n)],
        "rms_after_per_joint": [rms(a[:, j]) for j in range(n)],
    }
