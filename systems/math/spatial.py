"""Small spatial-algebra helpers shared by the regressors, the planner and the ARMOUR law.

Motion vectors are [ω; v] (6,), about the world origin unless said otherwise. These are plain
numpy on the last axis: np.cross's per-call overhead dominates on the small stacked vectors the
regressors evaluate, so the products are written out.
"""

from __future__ import annotations

import numpy as np

_CROSS3 = np.cross(np.eye(3)[:, None], np.eye(3)[None, :]).reshape(9, 3)  # a x b = vec(a bᵀ) @ _CROSS3


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (length 3), broadcasting, any dtype."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        -1,
    )


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b for (m, 3) arrays as one matrix product (fastest at a single sample)."""
    return (a[:, :, None] * b[:, None, :]).reshape(len(a), 9) @ _CROSS3


def to_body(R: np.ndarray, p: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Motion vectors about the world origin (..., 6) -> the body frames at (R (..., 3, 3), p (..., 3))."""
    w, u = x[..., :3], x[..., 3:]
    rt = np.swapaxes(R, -1, -2)
    return np.concatenate([(rt @ w[..., None])[..., 0], (rt @ (u + cross(w, p))[..., None])[..., 0]], -1)
