"""Model-side time laws of the time_delay effect: a pure delay (read the model d earlier) and
a first-order lag (the model low-passed), restarted where a lag's state is unknown.
"""

from __future__ import annotations

import numpy as np

from .design import Design


def _sample_shift(sample, idx, delay):
    """Interpolation weights reading sample-level quantities at t[idx] - delay inside the
    segment of each idx: X_delayed = (1 - w) X[j0] + w X[j1]; beyond a segment's ends the end
    interval is extended linearly (w < 0 or > 1; clipping there would bias whole momentum
    windows at every segment start). Only smooth model quantities are interpolated (never the
    noisy measurement), so a delay does not average noise away."""
    t, seg = sample["t"], sample["segment"][idx]
    lo, hi = sample["seg_bounds"][seg, 0], sample["seg_bounds"][seg, 1]
    ts = t[idx] - delay
    j0 = np.clip(np.searchsorted(t, ts, side="right") - 1, lo, np.maximum(hi - 1, lo))
    j1 = np.minimum(j0 + 1, hi)
    span = t[j1] - t[j0]
    w = np.where(span > 0, (ts - t[j0]) / np.where(span > 0, span, 1.0), 0.0)
    return j0, j1, w


def first_order_lag(
    t: np.ndarray, x: np.ndarray, seg_bounds: np.ndarray, d: float, *, chunk: float = 50.0
) -> np.ndarray:
    """y with d y' = x - y along t, per gap-free segment, exact for x linear between samples;
    each segment starts in the steady ramp (y = x - d x'). Works on (N, ...) arrays.

    Step k: y_k = a_k y_(k-1) + u_k, a_k = exp(-dt_k / d). Unrolled from an anchor sample p,
    y_j = exp(-(t_j - t_p)/d) (y_p + sum_(p<i<=j) u_i exp((t_i - t_p)/d)): a cumulative sum,
    re-anchored every `chunk` time constants so the exponentials stay far from overflow."""
    y = np.empty_like(x)
    for s0, s1 in seg_bounds:
        tt, xx = t[s0 : s1 + 1], x[s0 : s1 + 1]
        if len(tt) == 1:
            y[s0] = xx[0]
            continue
        col = (-1,) + (1,) * (x.ndim - 1)
        dt = np.diff(tt).reshape(col)
        a = np.exp(-dt / d)
        dx = np.diff(xx, axis=0)
        u = xx[1:] - a * xx[:-1] - dx * (d / dt) * (1 - a)
        ys = y[s0 : s1 + 1]
        ys[0] = xx[0] - d * dx[0] / dt[0]
        k = 1
        while k < len(tt):
            m = min(max(int(np.searchsorted(tt, tt[k - 1] + chunk * d, side="right")), k + 1), len(tt))
            grow = ((tt[k:m] - tt[k - 1]) / d).reshape(col)
            ys[k:m] = np.exp(-grow) * (ys[k - 1] + np.cumsum(u[k - 1 : m - 1] * np.exp(grow), axis=0))
            k = m
    return y


def restarted_lag(smp: dict, x: np.ndarray, lagged: np.ndarray, *, d: float, anchor: float | np.ndarray) -> np.ndarray:
    """The lag `lagged` = first_order_lag(x) restarted at smp["restarts"]: from each restart s
    of joint j on, the lagged output starts at anchor[s, j] (the measured torque for the
    nominal, 0 for effect columns, so the prediction there is the measurement) instead of the
    steady-start chain. Both chains obey d y' + y = x on the piece, so they differ by the free
    response (y_anchor - y_plain)(s) exp(-(t - s)/d).

    Momentum form (smp["antiderivative"]): x and lagged are antiderivatives X, Z (the lagged
    output is y = (X - Z)/d) and the free response enters integrated, d dy (1 - exp(-(t - s)/d)),
    carried across later restarts so window differences stay integrals of the restarted y."""
    t = smp["t"]
    out = lagged.copy()
    anchor = np.broadcast_to(np.asarray(anchor, float), x.shape[:2])  # (N, n): one value per sample and joint
    integrated = smp["antiderivative"]
    for j, starts in enumerate(smp["restarts"]):
        ends = np.append(starts[1:], len(t))
        offset = 0.0
        for s, e in zip(starts, ends):
            y_plain = (x[s, j] - lagged[s, j]) / d if integrated else lagged[s, j]
            jump = anchor[s, j] - y_plain
            decay = np.exp(-(t[s:e] - t[s]) / d).reshape((-1,) + (1,) * (x.ndim - 2))
            if integrated:
                out[s:e, j] += offset + d * jump * (1.0 - decay)
                if e < len(t):
                    offset = offset + d * jump * (1.0 - np.exp(-(t[e] - t[s]) / d))
            else:
                out[s:e, j] += jump * decay
    return out


def model_side_rows(design: Design, groups: list[str], transform: tuple[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """(A (R, n, K), nominal (R, n)) of a design with a time law applied to the model side:
    transform = ("shift", d): read d earlier; ("lag", d): first-order low-pass with time constant d.
    Sample-level quantities are transformed, then formed into rows (window differences in the
    momentum form: the lag commutes with the integral the samples hold)."""
    law, d = transform
    smp = design.sample
    nom = smp["nominal"]
    key = ("columns",) + tuple(groups)
    if key not in smp:  # the same column sets come back for every trial d
        smp[key] = np.concatenate([smp["cols"][g] for g in groups], -1) if groups else np.zeros(nom.shape + (0,))
    A = smp[key]
    if law == "lag":
        t, bounds = smp["t"], smp["seg_bounds"]
        A = restarted_lag(smp, A, first_order_lag(t, A, bounds, d), d=d, anchor=0.0)
        nom = restarted_lag(smp, nom, first_order_lag(t, nom, bounds, d), d=d, anchor=smp["measured"])

    def at(idx):
        if law == "lag":
            return A[idx], nom[idx]
        j0, j1, w = _sample_shift(smp, idx, d)
        return (
            (1 - w)[:, None, None] * A[j0] + w[:, None, None] * A[j1],
            (1 - w)[:, None] * nom[j0] + w[:, None] * nom[j1],
        )

    win = smp["windows"]
    if win is None:
        return (A, nom) if law == "lag" else at(np.arange(len(smp["t"])))
    (a0, n0), (a1, n1) = at(win[:, 0]), at(win[:, 1])
    span = (smp["t"][win[:, 1]] - smp["t"][win[:, 0]])[:, None]
    return (a1 - a0) / span[:, :, None], (n1 - n0) / span
