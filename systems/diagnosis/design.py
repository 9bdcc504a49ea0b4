"""One log in one residual form (a Design): residual rows, every effect's columns, gap-free
segments, time blocks and the speed-saturation mask.

Residual forms (one per diagnosis, chosen from the logs):
  inverse_dynamics  logs carry accelerations: r(t) = tau - W(q, v, a) theta0, one row per sample.
  momentum          no accelerations: over windows [t1, t2] of about `window_s` that never span a
                    time gap, r = (int tau dt - [Wm theta0]_t1^t2 + int Wc theta0 dt) / (t2 - t1)
                    (trapezoid), the window-mean torque residual, so nothing is differentiated.
  The smoothing differentiator (Savitzky-Golay, cubic, ~0.1 s window, per gap-free segment) is
  only used to compare (residual_forms) and to classify acceleration regimes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from safesysid.systems.model import regressors
from safesysid.systems.model.corrected_model import Saturation
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.robot_model import RobotModel

from .effects import STRIBECK_VELOCITIES

BLOCK_S = 0.5


SATURATION_BAND = 0.02  # rad/s: |v| pinned inside this band ...
SATURATION_MIN_S = 0.2  # ... for at least this long ...
SATURATION_LEVEL = 0.97  # ... at the joint's top speed over all logs (fraction of max |v|)
Segments = list[tuple[int, int]]  # inclusive index ranges of gap-free pieces


WINDOW_S = 0.1  # momentum-form window


# ---- per-log preparation --------------------------------------------------------------------
def segments(t: np.ndarray, max_gap_s: float | None = None) -> Segments:
    """Index ranges [(i0, i1)] (inclusive) of gap-free pieces; a gap is a step > max_gap_s
    (default 5 median steps)."""
    dt = np.diff(t)
    if max_gap_s is None:
        max_gap_s = 5.0 * float(np.median(dt)) if len(dt) else np.inf
    cuts = np.flatnonzero(dt > max_gap_s)
    starts = np.concatenate([[0], cuts + 1])
    ends = np.concatenate([cuts, [len(t) - 1]])
    return [(int(a), int(b)) for a, b in zip(starts, ends)]


def smooth_derivative(
    t: np.ndarray, x: np.ndarray, segs: Segments, *, window_s: float = 0.1, order: int = 3
) -> np.ndarray:
    """Savitzky-Golay derivative of x (N, ...) along t, per gap-free segment (np.gradient when
    a segment is too short). The documented differentiator used only where a derivative is needed."""
    from scipy.signal import savgol_filter

    out = np.empty_like(np.asarray(x, float))
    for i0, i1 in segs:
        tt, xx = t[i0 : i1 + 1], x[i0 : i1 + 1]
        if len(tt) < 2:
            out[i0 : i1 + 1] = 0.0
            continue
        h = float(np.median(np.diff(tt)))
        w = int(round(window_s / h)) | 1
        w = max(w, order + 2 + (order % 2 == 0))
        if len(tt) >= w:
            out[i0 : i1 + 1] = savgol_filter(xx, w, order, deriv=1, delta=h, axis=0)
        else:
            out[i0 : i1 + 1] = np.gradient(xx, tt, axis=0)
    return out


def _windows(t, segs, window_s):
    """Non-overlapping windows (i0, i1) of about window_s inside each segment."""
    out = []
    for s0, s1 in segs:
        if s1 <= s0:
            continue
        h = float(np.median(np.diff(t[s0 : s1 + 1])))
        step = max(1, int(round(window_s / h)))
        edges = list(range(s0, s1 + 1, step))
        if edges[-1] != s1:
            if s1 - edges[-1] < step // 2 and len(edges) > 1:
                edges[-1] = s1
            else:
                edges.append(s1)
        out.extend(zip(edges[:-1], edges[1:]))
    return np.array(out, int).reshape(-1, 2)


def _cumtrapz(t, x):
    """Cumulative trapezoid along axis 0 (integrals between any two samples by difference)."""
    dt = np.diff(t).reshape((-1,) + (1,) * (x.ndim - 1))
    c = np.zeros_like(x, dtype=float)
    c[1:] = np.cumsum(0.5 * (x[1:] + x[:-1]) * dt, axis=0)
    return c


def _gravity(tree, theta_b, q, gravity=None):
    if gravity is not None:
        tree = dataclasses.replace(tree, gravity=np.asarray(gravity, float))
    z = np.zeros_like(q)
    return regressors.standard_regressor(tree, q, z, z) @ theta_b


def _neighbour_mean(x, segs):
    """(x[i-1] + x[i+1]) / 2 inside segments: a smooth-signal estimate that shares no white
    measurement noise with x[i] (so a column built from it is not correlated with the
    residual's own noise)."""
    out = np.empty_like(x)
    for s0, s1 in segs:
        seg = x[s0 : s1 + 1]
        if len(seg) < 3:
            out[s0 : s1 + 1] = seg
            continue
        o = out[s0 : s1 + 1]
        o[1:-1] = 0.5 * (seg[:-2] + seg[2:])
        o[0], o[-1] = seg[1], seg[-2]
    return out


def _diag(x):
    """(N, n) -> (N, n, n) with x on the diagonal (per-joint effect columns)."""
    n = x.shape[1]
    out = np.zeros(x.shape + (n,))
    idx = np.arange(n)
    out[:, idx, idx] = x
    return out


@dataclass
class Design:
    """One log in one residual form: residual rows y (R, n) and effect columns (R, n, k)."""

    form: str
    y: np.ndarray
    cols: dict[str, np.ndarray]  # group name -> (R, n, k)
    row_time: np.ndarray  # (R,) time of each row (window middle)
    row_block: np.ndarray  # (R,) block id (BLOCK_S pieces, never across gaps)
    features: dict[str, np.ndarray]  # v, a, g, q per row (R, n) for regimes and pose bins
    tau_hat_nominal: np.ndarray  # (R, n) nominal model torque (row form)
    source: str = ""
    row_segment: np.ndarray | None = None  # (R,) gap-free segment of each row
    row_saturated: np.ndarray | None = None  # (R, n) joint speed-saturated inside the row (see velocity_saturation)
    sample: dict | None = None  # sample-level model quantities for time laws (see model_side_rows)
    residual_forms: dict[str, float] = field(default_factory=dict)
    segments: Segments = field(default_factory=list)
    cache: dict = field(default_factory=dict)  # flattened rows and normal equations per time law


def saturation_rule(logs: Sequence[JointLog]) -> Saturation:
    """The speed-saturation rule with each joint's top speed taken from `logs` (the fit logs:
    the rule is frozen there and stored in corrected_model.yaml, never re-derived on check logs)."""
    top = np.max([np.abs(l.v).max(0) for l in logs], axis=0)
    return Saturation([float(x) for x in top], SATURATION_LEVEL, SATURATION_BAND, SATURATION_MIN_S)


def velocity_saturation(logs: Sequence[JointLog], rule: Saturation | None = None) -> list[np.ndarray]:
    """(N, n) masks per log: joint j's velocity pinned at its top speed, i.e. |v_j| stays inside
    a `band` for >= `min_duration` (gap-free, one sign) at >= `level` of the joint's top speed
    (rule: corrected_model.Saturation; default saturation_rule(logs)). A drive at its speed
    limit does not deliver the logged torque command: on the real Gen3 logs the torque swings
    by 36 N m while v stays at 1.73 rad/s and the acceleration at zero. Such samples obey no
    model of the arm; they are left out of fitting and selection and reported apart."""
    rule = rule or saturation_rule(logs)
    vmax = np.asarray(rule.top_speed_rad_s, float)
    masks = []
    for l in logs:
        mask = np.zeros(l.v.shape, bool)
        for s0, s1 in segments(l.t):
            for j in range(l.v.shape[1]):
                v = l.v[s0 : s1 + 1, j]
                av = np.abs(v)
                cand = av >= rule.level * vmax[j]
                i, N = 0, len(v)
                while i < N:
                    if not cand[i]:
                        i += 1
                        continue
                    k, lo, hi = i, av[i], av[i]
                    while (
                        k + 1 < N
                        and cand[k + 1]
                        and np.sign(v[k + 1]) == np.sign(v[i])
                        and max(hi, av[k + 1]) - min(lo, av[k + 1]) <= rule.band_rad_s
                    ):
                        k += 1
                        lo, hi = min(lo, av[k]), max(hi, av[k])
                    if l.t[s0 + k] - l.t[s0 + i] >= rule.min_duration_s:
                        mask[s0 + i : s0 + k + 1, j] = True
                    i = k + 1
        masks.append(mask)
    return masks


def build_design(
    model: RobotModel,
    log: JointLog,
    form: str,
    *,
    window_s: float = 0.1,
    max_gap_s: float | None = None,
    columns: bool = True,
    saturated: np.ndarray | None = None,
) -> Design:
    """Residual rows and every effect's columns for one JointLog (see module docstring).
    `saturated`: (N, n) sample mask of velocity_saturation (default: none)."""
    t, q, v = log.t, log.q, log.v
    segs = segments(t, max_gap_s)
    a_smooth = smooth_derivative(t, v, segs)
    g = _gravity(model.tree, model.theta[: 10 * model.n], q)
    std_cols = _effect_columns(model, log, form=form, segs=segs, a_smooth=a_smooth) if columns else {}
    if form == "inverse_dynamics":
        rows = _inverse_dynamics_rows(model, log, std_cols, segs=segs, g=g, columns=columns)
    elif form == "momentum":
        rows = _momentum_rows(
            model, log, std_cols, segs=segs, g=g, a_smooth=a_smooth, window_s=window_s, columns=columns
        )
    else:
        raise ValueError(f"unknown residual form {form!r}")
    return _design(form, log, rows, segs=segs, saturated=saturated)


class _Rows(NamedTuple):
    y: np.ndarray  # residual rows
    cols: dict  # effect name -> columns per row
    tau_nom: np.ndarray
    rows: np.ndarray  # the sample each row sits at
    row_time: np.ndarray
    feat: dict
    sample_cols: dict
    sample_nominal: np.ndarray
    win: np.ndarray | None  # momentum windows (sample index pairs), None per sample


def _effect_columns(model, log, *, form, segs, a_smooth):
    """Every sample-level effect column but the form-specific ones (friction laws, load friction,
    offset, base tilt, joint elasticity)."""
    n, tree = model.n, model.tree
    q, v, tau = log.q, log.v, log.tau
    theta_b = model.theta[: 10 * n]
    gnorm = float(np.linalg.norm(tree.gravity)) or 9.81
    sgn = regressors.coulomb_shape(v, model.coulomb_smoothing)
    std_cols = {"coulomb_friction": _diag(sgn), "viscous_friction": _diag(v)}
    for vs in STRIBECK_VELOCITIES:
        std_cols[f"stribeck_friction@{vs}"] = _diag(sgn * np.exp(-((v / vs) ** 2)))
    tau_nb = _neighbour_mean(tau, segs)
    std_cols["load_friction"] = _diag(np.abs(tau_nb) * sgn)
    std_cols["torque_offset"] = _diag(np.ones_like(v))
    std_cols["base_tilt"] = np.stack(
        [_gravity(tree, theta_b, q, [gnorm, 0, 0]), _gravity(tree, theta_b, q, [0, gnorm, 0])], -1
    )
    # d tau_rigid / dq at the logged motion (acceleration: logged, else the smoothed one).
    h = 1e-6
    a_el = log.a if (form == "inverse_dynamics" and log.a is not None) else a_smooth
    tau0 = regressors.standard_regressor(tree, q, v, a_el) @ theta_b
    dtdq = np.stack(
        [(regressors.standard_regressor(tree, q + h * np.eye(n)[j], v, a_el) @ theta_b - tau0) / h for j in range(n)],
        -1,
    )
    # Torque through the transmission: measured minus the nominal joint friction.
    jp = model.joint_params
    fric = jp.coulomb * sgn + jp.viscous * v + jp.offset
    std_cols["joint_elasticity"] = -dtdq * (tau_nb - fric)[:, None, :]
    return std_cols


def _inverse_dynamics_rows(model, log, std_cols, *, segs, g, columns):
    """One row per sample: measured minus the model's inverse dynamics at the logged acceleration."""
    t, q, v, tau, a = log.t, log.q, log.v, log.tau, log.a
    W = model.standard_regressor(q, v, a)
    tau_nom = W @ model.theta
    y = tau - tau_nom
    cols = dict(std_cols)
    if columns:
        cols["torque_scale"] = _diag(tau_nom)
        cols["armature"] = _diag(a)
        cols["payload"] = W[:, :, model.ee_slice]
        # Savitzky-Golay derivative: zero weight on the centre sample, so the column shares
        # no white noise with the residual row.
        cols["time_delay"] = -smooth_derivative(t, tau, segs)[:, :, None]
        cols["time_delay@shift"] = np.zeros(y.shape + (0,))
    feat = {"v": v, "a": a, "g": g, "q": q}
    return _Rows(y, cols, tau_nom, np.arange(len(t)), t, feat, cols, tau_nom, None)


def _momentum_rows(model, log, std_cols, *, segs, g, a_smooth, window_s, columns):
    """One row per window: the momentum balance's residual over it, divided by its span."""
    t, q, v, tau = log.t, log.q, log.v, log.tau
    win = _windows(t, segs, window_s)
    i0, i1 = win[:, 0], win[:, 1]
    span = (t[i1] - t[i0])[:, None]
    Wm = model.momentum_regressor(q, v)
    Wc = model.momentum_rate_regressor(q, v)
    pm = Wm @ model.theta
    cc = _cumtrapz(t, Wc @ model.theta)
    ct = _cumtrapz(t, tau)
    y = (ct[i1] - ct[i0] - (pm[i1] - pm[i0]) + (cc[i1] - cc[i0])) / span
    tau_nom = ((pm[i1] - pm[i0]) - (cc[i1] - cc[i0])) / span
    # Each column as a sample-level "antiderivative" C; the window row is (C[i1] - C[i0]) / span.
    cum = {}
    if columns:
        for name, c in std_cols.items():
            cum[name] = _cumtrapz(t, c)
        cum["torque_scale"] = _diag(pm - cc)
        cum["armature"] = _diag(v)
        cum["payload"] = Wm[:, :, model.ee_slice] - _cumtrapz(t, Wc[:, :, model.ee_slice])
        cum["time_delay"] = -tau[:, :, None]
        cum["time_delay@shift"] = np.zeros(tau.shape + (0,))
    s3 = span[:, :, None]
    cols = {name: (c[i1] - c[i0]) / s3 for name, c in cum.items()}
    rows = (i0 + i1) // 2
    feat = {"v": v[rows], "a": a_smooth[rows], "g": g[rows], "q": q[rows]}
    return _Rows(y, cols, tau_nom, rows, 0.5 * (t[i0] + t[i1]), feat, cum, pm - cc, win)


def _design(form, log, r, *, segs, saturated):
    """The Design of rows r: held-out blocks (BLOCK_S pieces inside each segment), saturated rows
    and the sample-level data."""
    t, v = log.t, log.v
    seg_id = np.zeros(len(t), int)
    for k, (s0, s1) in enumerate(segs):
        seg_id[s0 : s1 + 1] = k
    blk = seg_id[r.rows] * 100000 + np.floor((r.row_time - t[0]) / BLOCK_S).astype(int)
    _, row_block = np.unique(blk, return_inverse=True)
    d = Design(form, r.y, r.cols, r.row_time, row_block, r.feat, r.tau_nom, log.source, segments=segs)
    d.row_segment = seg_id[r.rows]
    sat = np.zeros(v.shape, bool) if saturated is None else np.asarray(saturated, bool)
    if r.win is None:
        d.row_saturated = sat[r.rows]
    else:  # a window is saturated when any of its samples is
        csum = np.concatenate([np.zeros((1, v.shape[1]), int), np.cumsum(sat, 0)])
        d.row_saturated = (csum[r.win[:, 1] + 1] - csum[r.win[:, 0]]) > 0
    d.sample = {
        "t": t,
        "segment": seg_id,
        "seg_bounds": np.array(segs, int).reshape(-1, 2),
        "cols": r.sample_cols,
        "nominal": r.sample_nominal,
        "windows": r.win,
        "measured": log.tau,
        "restarts": lag_restarts(segs, sat),
        "antiderivative": r.win is not None,
    }
    return d


def lag_restarts(segs: Segments, saturated: np.ndarray) -> list[np.ndarray]:
    """Per joint, the samples where a lag's state is unknown and is taken from the measured
    torque instead: every segment start (the history before a log or a gap is not logged) and
    the first sample after a speed-saturated span (there the logged torque is not what the
    joint received, so the filter state the model carries is wrong). [array of indices] * n."""
    n = saturated.shape[1]
    starts = [s0 for s0, _ in segs]
    out = []
    for j in range(n):
        after = np.flatnonzero(saturated[:-1, j] & ~saturated[1:, j]) + 1
        out.append(np.unique(np.concatenate([starts, after])).astype(int))
    return out


def residual_forms(model: RobotModel, log: JointLog) -> dict[str, float]:
    """RMS of the nominal residual in each form: logged acceleration (if any), smoothed
    derivative of v (Savitzky-Golay) and the momentum form (window means)."""
    out = {}
    segs = segments(log.t)
    theta = model.theta
    if log.a is not None:
        out["inverse_dynamics_logged_a"] = rms(log.tau - model.standard_regressor(log.q, log.v, log.a) @ theta)
    a_s = smooth_derivative(log.t, log.v, segs)
    out["inverse_dynamics_smoothed_a"] = rms(log.tau - model.standard_regressor(log.q, log.v, a_s) @ theta)
    out["momentum_window_mean"] = rms(build_design(model, log, "momentum", columns=False).y)
    return out


def rms(x: np.ndarray, axis: int | None = None) -> float | np.ndarray:
    return float(np.sqrt(np.mean(np.square(x)))) if axis is None else np.sqrt(np.mean(np.square(x), axis=axis))


def choose_form(logs: Sequence[JointLog]) -> str:
    return "inverse_dynamics" if all(l.a is not None for l in logs) else "momentum"
