"""Sim-to-real gap diagnosis: residual of a nominal model, where it lies, which effect explains it.

Pure math on (RobotModel, joint logs). The CLI (app/diagnose_cli.py) and the self-check
(systems/gap_simulate.py) call `diagnose`.

Residual forms (one per diagnosis, chosen from the logs):
  inverse_dynamics  logs carry accelerations: r(t) = tau - W(q, v, a) theta0, one row per sample.
  momentum          no accelerations: over windows [t1, t2] of about `window_s` that never span a
                    time gap, r = (int tau dt - [Wm theta0]_t1^t2 + int Wc theta0 dt) / (t2 - t1)
                    (trapezoid), the window-mean torque residual, so nothing is differentiated.
  The smoothing differentiator (Savitzky-Golay, cubic, ~0.1 s window, per gap-free segment) is
  only used to compare (gap.residual_forms) and to classify acceleration regimes.

Every effect is linear (or linearized) in its parameters p: r = Phi p, with Phi built from the
log in the same residual form (terms in the acceleration are integrated exactly: int a dt = dv,
int W_e dt = [Wm_e] - int Wc_e dt, int tau_dot dt = d tau). Effects and their physical model:
  coulomb_friction   dFc_j sgn(v_j)                          Fc0 + dFc >= 0
  viscous_friction   dFv_j v_j                               Fv0 + dFv >= 0
  stribeck_friction  Fs_j sgn(v_j) exp(-(v_j/vs)^2)          Fs >= 0, vs from a grid (shared)
  load_friction      mu_j |tau_j| sgn(v_j)                   0 <= mu <= MAX_LOAD_FRICTION; friction that
                                                             grows with the transmitted torque (gear
                                                             teeth, harmonic drives); tau_j from
                                                             neighbouring samples (no shared noise)
  armature           dIa_j a_j                               Ia0 + dIa >= 0
  torque_offset      b_j                                     sensor offset
  torque_scale       (s_j - 1) tau_nominal_j                 tau_meas = s tau_true (first order in the
                                                             other effects; regressing on tau_meas itself
                                                             would let it soak up any residual)
  payload            W_e(q, v, a) dtheta_e (10 params)       theta_e0 + dtheta_e physically
                                                             consistent (log-Cholesky), dm >= 0
  time_delay         two laws, the better fit is kept; both act on the model side (nominal + all
                     effect rows), never on the noisy measurement; d on a 5 ms grid (walked on to
                     an interior minimum), refined by a parabola:
                     pure delay: model read d earlier        tau_meas(t) = tau_true(t - d), |d| <= 0.2 s
                     d < 0: torque leads the motion (actuation delay: the sensor sees the motor
                     torque before it reaches the joint); d > 0: the measurement lags
                     first-order lag: model low-passed       tau_meas + d dtau_meas/dt = tau_true,
                     (exact for piecewise-linear samples)    0 < d <= 0.2 s (a filtered torque signal)
                     The grid is centred on the linear estimate from -d dtau_meas/dt (Savitzky-Golay).
                     A lag has a state: where its history is unknown (a segment start) or the
                     logged torque was not what the joint received (after a speed-saturated span)
                     the lagged model restarts from the measured torque (restarted_lag).
  base_tilt          G(q; g_x) x + G(q; g_y) y               gravity gains horizontal parts (x, y)|g|
  joint_elasticity   -(d tau_rigid/dq_j) tau_s,j c_j         link angle q - tau_s/k, c = 1/k >= 0, tau_s =
                                                             tau_meas - nominal friction (transmitted)
                                                             (quasi-static deflection under load; tau_j
                                                             from neighbouring samples, no shared noise)
Fits are bounded linear least squares (scipy lsq_linear on the Cholesky factor of the normal
equations, so each fit costs microseconds); the payload uses a log-Cholesky Gauss-Newton
(scipy least_squares) when the linear fit is not physically consistent.

Honest protocol (diagnose): every selection step and threshold uses the fit logs only. Inner
folds on them (leave one fit log out; TIME_FOLDS contiguous time pieces when there is one fit
log) fit each candidate set on the training folds and score it on the validation fold; the
validation residuals, concatenated (each fit-log sample validated once), are what the rules
below call "held-out". The speed-saturation top speeds come from the fit logs too. The selected
set is refitted on all fit logs; the check logs are scored once with that frozen selection and
its parameters (`test`), through design_residual, the function that also scores a
corrected_model.yaml (score).

Selection is forward-greedy: the candidate with the largest held-out improvement is added while
it is significant, i.e. all of
  (1) held-out (validation) squared residual drops by more than Z_BLOCK standard errors of its
      random part (see `significance`; blocks of BLOCK_S seconds, so autocorrelated residuals
      do not fake significance), or the drop is consistent across blocks: a Wilcoxon
      signed-rank test of the per-block gains at the same 3-sigma level (P_BLOCKS). The first
      credits effects acting in bursts; the second effects that improve nearly every block
      while the residual left is heavy-tailed (real logs with unmodelled transients, whose
      few large blocks inflate the standard error),
  (2) the drop exceeds MIN_RELATIVE of the current validation mean square and MIN_NOISE_FRACTION
      of the noise variance (robust estimate from first differences of the validation residual):
      improvement beyond what measurement noise explains,
  (3) BIC on the inner training folds decreases,
  (4) relevance: on its most affected joint the effect changes the predicted torque by at
      least MIN_EFFECT_RATIO of the measured torque RMS (0.25 %, well below torque-sensor
      accuracy): a statistically clear but physically negligible mismatch, such as a
      simulator's own time discretisation, is not a cause.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from . import inertial, regressors

EFFECTS = (
    "coulomb_friction",
    "viscous_friction",
    "stribeck_friction",
    "load_friction",
    "armature",
    "torque_offset",
    "torque_scale",
    "payload",
    "time_delay",
    "base_tilt",
    "joint_elasticity",
)
PER_JOINT = (
    "coulomb_friction",
    "viscous_friction",
    "stribeck_friction",
    "load_friction",
    "armature",
    "torque_offset",
    "torque_scale",
    "joint_elasticity",
)
STRIBECK_VELOCITIES = tuple(round(0.02 * 1.5**k, 4) for k in range(7))  # rad/s grid for vs (0.02..0.23)
TIME_LAWS = {"time_delay@shift": "shift", "time_delay@lag": "lag"}  # model-side time laws (grid-searched d)
BLOCK_S = 0.5
Z_BLOCK = 3.0
P_BLOCKS = 0.00135  # one-sided p of the block signed-rank test: the same 3-sigma level as Z_BLOCK
MIN_BLOCKS = 12  # fewer blocks cannot reach P_BLOCKS reliably: the rank test then abstains
MIN_RELATIVE = 0.01
MIN_NOISE_FRACTION = 0.05
MIN_EFFECT_RATIO = 0.0025  # effect RMS / measured torque RMS on its most affected joint
MAX_DELAY_S = 0.2
DELAY_FINE_S = 0.005
MAX_TILT = 0.2
MAX_COMPLIANCE = 0.02  # rad/(N m)
MAX_LOAD_FRICTION = 0.5  # friction torque per unit transmitted torque
REGIME_QUANTILE = 0.75
SATURATION_BAND = 0.02  # rad/s: |v| pinned inside this band ...
SATURATION_MIN_S = 0.2  # ... for at least this long ...
SATURATION_LEVEL = 0.97  # ... at the joint's top speed over all logs (fraction of max |v|)


# ---- BLAS threads ---------------------------------------------------------------------------
def single_threaded_blas():
    """Run with one BLAS thread (threadpoolctl, as a context manager): the design matrices are
    tall and thin, and on a shared machine a threaded GEMM of that shape measured ~500x slower
    (spinning threads)."""
    return threadpool_limits(limits=1, user_api="blas")


# ---- per-log preparation --------------------------------------------------------------------
def segments(t, max_gap_s=None):
    """Index ranges [(i0, i1)] (inclusive) of gap-free pieces; a gap is a step > max_gap_s
    (default 5 median steps)."""
    dt = np.diff(t)
    if max_gap_s is None:
        max_gap_s = 5.0 * float(np.median(dt)) if len(dt) else np.inf
    cuts = np.flatnonzero(dt > max_gap_s)
    starts = np.concatenate([[0], cuts + 1])
    ends = np.concatenate([cuts, [len(t) - 1]])
    return [(int(a), int(b)) for a, b in zip(starts, ends)]


def smooth_derivative(t, x, segs, window_s=0.1, order=3):
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
    cols: dict  # group name -> (R, n, k)
    row_time: np.ndarray  # (R,) time of each row (window middle)
    row_block: np.ndarray  # (R,) block id (BLOCK_S pieces, never across gaps)
    features: dict  # v, a, g per row (R, n) for regimes
    tau_hat_nominal: np.ndarray  # (R, n) nominal model torque (row form)
    source: str = ""
    row_segment: np.ndarray = None  # (R,) gap-free segment of each row
    row_saturated: np.ndarray = None  # (R, n) joint speed-saturated inside the row (see velocity_saturation)
    sample: dict = None  # sample-level model quantities for time laws (see model_side_rows)
    residual_forms: dict = field(default_factory=dict)
    segments: list = field(default_factory=list)
    cache: dict = field(default_factory=dict)  # flattened rows and normal equations per time law


def saturation_rule(logs):
    """The speed-saturation rule with each joint's top speed taken from `logs` (the fit logs:
    the rule is frozen there and stored in corrected_model.yaml, never re-derived on check logs)."""
    from .corrected_model import Saturation

    top = np.max([np.abs(l.v).max(0) for l in logs], axis=0)
    return Saturation([float(x) for x in top], SATURATION_LEVEL, SATURATION_BAND, SATURATION_MIN_S)


def velocity_saturation(logs, rule=None):
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


def build_design(model, log, form, window_s=0.1, max_gap_s=None, columns=True, saturated=None):
    """Residual rows and every effect's columns for one JointLog (see module docstring).
    `saturated`: (N, n) sample mask of velocity_saturation (default: none)."""
    n = model.n
    t, q, v, tau = log.t, log.q, log.v, log.tau
    nb = 10 * n
    theta, theta_b = model.theta, model.theta[:nb]
    tree = model.tree
    segs = segments(t, max_gap_s)
    a_smooth = smooth_derivative(t, v, segs)
    g = _gravity(tree, theta_b, q)
    gnorm = float(np.linalg.norm(tree.gravity)) or 9.81
    sgn = regressors.coulomb_shape(v, model.coulomb_smoothing)
    std_cols = {}
    if columns:
        std_cols["coulomb_friction"] = _diag(sgn)
        std_cols["viscous_friction"] = _diag(v)
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
            [
                (regressors.standard_regressor(tree, q + h * np.eye(n)[j], v, a_el) @ theta_b - tau0) / h
                for j in range(n)
            ],
            -1,
        )
        # Torque through the transmission: measured minus the nominal joint friction.
        jp = model.joint_params
        fric = jp.coulomb * sgn + jp.viscous * v + jp.offset
        std_cols["joint_elasticity"] = -dtdq * (tau_nb - fric)[:, None, :]
    ee = [model.end_effector]
    if form == "inverse_dynamics":
        a = log.a
        W = model.standard_regressor(q, v, a)
        tau_nom = W @ theta
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
        rows = np.arange(len(t))
        row_time = t
        feat = {"v": v, "a": a, "g": g}
        sample_cols, sample_nominal, win = cols, tau_nom, None
    elif form == "momentum":
        win = _windows(t, segs, window_s)
        i0, i1 = win[:, 0], win[:, 1]
        span = (t[i1] - t[i0])[:, None]
        Wm = model.momentum_regressor(q, v)
        Wc = model.momentum_rate_regressor(q, v)
        pm = Wm @ theta
        cc = _cumtrapz(t, Wc @ theta)
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
        row_time = 0.5 * (t[i0] + t[i1])
        feat = {"v": v[rows], "a": a_smooth[rows], "g": g[rows]}
        sample_cols, sample_nominal = cum, pm - cc
        del ee
    else:
        raise ValueError(f"unknown residual form {form!r}")
    # Blocks for the held-out standard error: BLOCK_S pieces inside each segment.
    seg_id = np.zeros(len(t), int)
    for k, (s0, s1) in enumerate(segs):
        seg_id[s0 : s1 + 1] = k
    blk = seg_id[rows] * 100000 + np.floor((row_time - t[0]) / BLOCK_S).astype(int)
    _, row_block = np.unique(blk, return_inverse=True)
    d = Design(form, y, cols, row_time, row_block, feat, tau_nom, log.source, segments=segs)
    d.row_segment = seg_id[rows]
    sat = np.zeros(v.shape, bool) if saturated is None else np.asarray(saturated, bool)
    if win is None:
        d.row_saturated = sat[rows]
    else:  # a window is saturated when any of its samples is
        csum = np.concatenate([np.zeros((1, n), int), np.cumsum(sat, 0)])
        d.row_saturated = (csum[win[:, 1] + 1] - csum[win[:, 0]]) > 0
    d.sample = {
        "t": t,
        "segment": seg_id,
        "seg_bounds": np.array(segs, int).reshape(-1, 2),
        "cols": sample_cols,
        "nominal": sample_nominal,
        "windows": win,
        "measured": tau,
        "restarts": lag_restarts(segs, sat),
        "antiderivative": win is not None,
    }
    return d


def lag_restarts(segs, saturated):
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


def first_order_lag(t, x, seg_bounds, d, chunk=50.0):
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


def restarted_lag(smp, x, lagged, d, anchor):
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


def model_side_rows(design, groups, transform):
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
        A = restarted_lag(smp, A, first_order_lag(t, A, bounds, d), d, 0.0)
        nom = restarted_lag(smp, nom, first_order_lag(t, nom, bounds, d), d, smp["measured"])

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


def residual_forms(model, log):
    """RMS of the nominal residual in each form: logged acceleration (if any), smoothed
    derivative of v (Savitzky-Golay) and the momentum form (window means)."""
    out = {}
    segs = segments(log.t)
    theta = model.theta
    if log.a is not None:
        out["inverse_dynamics_logged_a"] = _rms(log.tau - model.standard_regressor(log.q, log.v, log.a) @ theta)
    a_s = smooth_derivative(log.t, log.v, segs)
    out["inverse_dynamics_smoothed_a"] = _rms(log.tau - model.standard_regressor(log.q, log.v, a_s) @ theta)
    out["momentum_window_mean"] = _rms(build_design(model, log, "momentum", columns=False).y)
    return out


def _rms(x, axis=None):
    return float(np.sqrt(np.mean(np.square(x)))) if axis is None else np.sqrt(np.mean(np.square(x), axis=axis))


# ---- effect groups, bounds, fitting ---------------------------------------------------------
def effect_groups(effect):
    """Column groups that realise an effect (Stribeck: one per grid velocity, alternatives)."""
    if effect == "stribeck_friction":
        return [f"stribeck_friction@{vs}" for vs in STRIBECK_VELOCITIES]
    if effect == "time_delay":  # a pure delay or a first-order lag (see TIME_LAWS)
        return list(TIME_LAWS)
    return [effect]


def group_bounds(model, group, k):
    jp = model.joint_params
    inf = np.inf
    name = group.split("@")[0]
    if name == "coulomb_friction":
        return -np.maximum(jp.coulomb, 0), np.full(k, inf)
    if name == "viscous_friction":
        return -np.maximum(jp.viscous, 0), np.full(k, inf)
    if name == "armature":
        return -np.maximum(jp.armature, 0), np.full(k, inf)
    if name == "stribeck_friction":
        return np.zeros(k), np.full(k, inf)
    if name == "torque_scale":
        return np.full(k, -0.5), np.full(k, 1.0)
    if name == "time_delay":
        return np.full(k, -MAX_DELAY_S), np.full(k, MAX_DELAY_S)
    if name == "base_tilt":
        return np.full(k, -MAX_TILT), np.full(k, MAX_TILT)
    if name == "joint_elasticity":
        return np.zeros(k), np.full(k, MAX_COMPLIANCE)
    if name == "load_friction":
        return np.zeros(k), np.full(k, MAX_LOAD_FRICTION)
    if name == "payload":
        lo = np.full(k, -inf)
        lo[0] = 0.0  # added mass >= 0
        return lo, np.full(k, inf)
    return np.full(k, -inf), np.full(k, inf)


# ---- rows of one design, cached on it -------------------------------------------------------
def _group_slices(design):
    """Column offset of each group in the design's flattened rows (cols order)."""
    if "slices" not in design.cache:
        out, start = {}, 0
        for g, c in design.cols.items():
            out[g] = slice(start, start + c.shape[-1])
            start += c.shape[-1]
        design.cache["slices"] = out
    return design.cache["slices"]


def _flat_rows(design):
    """(A (R n, K) of every group, y (R n,), valid (R n,)): row-major (row, joint) elements;
    valid = not speed-saturated (velocity_saturation)."""
    if "flat" not in design.cache:
        K = sum(c.shape[-1] for c in design.cols.values())
        A = np.concatenate(list(design.cols.values()), -1).reshape(-1, K)
        design.cache["flat"] = (A, design.y.reshape(-1), ~design.row_saturated.reshape(-1))
    return design.cache["flat"]


def design_rows(design, transform, groups):
    """(A (R n, k), y (R n,)) for `groups` with a model-side time law (None, ("shift", d) or
    ("lag", d)): with a law the columns of `groups` and the nominal torque move, the
    measurement stays (model_side_rows)."""
    if transform is None:
        A, y, _ = _flat_rows(design)
        sl = _group_slices(design)
        cols = [np.arange(sl[g].start, sl[g].stop) for g in groups]
        return A[:, np.concatenate(cols) if cols else np.zeros(0, int)], y
    moving = [g for g in groups if design.cols[g].shape[-1]]
    A, nominal = model_side_rows(design, moving, transform)
    y = (design.y + design.tau_hat_nominal - nominal).reshape(-1)
    return A.reshape(A.shape[0] * A.shape[1], A.shape[-1]), y


def design_normal(design, transform):
    """(G, b, y'y, rows) of the valid elements of one design, every group, one time law:
    formed once per design and law (a time-law search revisits the same d across folds and
    effect sets) and summed over the logs of a fit."""
    key = ("normal", transform)
    if key not in design.cache:
        A, y = design_rows(design, transform, list(design.cols))
        valid = _flat_rows(design)[2]
        A, y = A[valid], y[valid]
        design.cache[key] = (A.T @ A, A.T @ y, float(y @ y), int(valid.sum()))
    return design.cache[key]


def design_residual(design, params):
    """Residual (R, n) of one design on every element after the effects `params`
    ({group: array}; a TIME_LAWS group carries d). The one function that scores a set of
    effects on a log: selection (inner folds), the check logs and a frozen corrected model."""
    groups = [g for g in params if g not in TIME_LAWS]
    timed = [g for g in params if g in TIME_LAWS]
    transform = (TIME_LAWS[timed[0]], float(params[timed[0]][0])) if timed else None
    A, y = design_rows(design, transform, groups)
    p = np.concatenate([params[g] for g in groups]) if groups else np.zeros(0)
    return (y - A @ p).reshape(design.y.shape)


class Problem:
    """Fit designs (their normal equations, summed) and check designs (scored element-wise)."""

    def __init__(self, model, fit, check):
        self.model = model
        self.fit, self.check = list(fit), list(check)
        self.groups = list(fit[0].cols)
        self.k = {g: fit[0].cols[g].shape[-1] for g in self.groups}
        self.offset = {}
        start = 0
        for g in self.groups:
            self.offset[g] = start
            start += self.k[g]
        self.K = start
        n = fit[0].y.shape[1]
        self.n = n
        # Rows where a joint is speed-saturated obey no model (velocity_saturation): fitting and
        # selection use the valid elements only; reports also give the all-sample residual.
        G, b, yy, rows = design_normal(fit[0], None)
        for d in fit[1:]:
            Gd, bd, yyd, rd = design_normal(d, None)
            G, b, yy, rows = G + Gd, b + bd, yy + yyd, rows + rd
        self.G, self.b, self.yy, self.n_fit_rows = G, b, yy, rows
        self.check_valid = np.concatenate([_flat_rows(d)[2] for d in check]) if check else np.zeros(0, bool)
        self.y_check_all = np.concatenate([d.y.reshape(-1) for d in check]) if check else np.zeros(0)
        self.y_check = self.y_check_all[self.check_valid]
        # Row-major flattening: element (row, joint); blocks numbered across check logs.
        blocks, base = [], 0
        for d in check:
            blocks.append(np.repeat(d.row_block + base, n))
            base += d.row_block.max() + 1
        self.check_block = np.concatenate(blocks)[self.check_valid] if check else np.zeros(0, int)
        self.check_joint = np.tile(np.arange(n), len(self.y_check_all) // n)[self.check_valid]
        tau_check = np.concatenate([d.y + d.tau_hat_nominal for d in check]) if check else np.zeros((1, n))
        self.tau_rms_check = np.sqrt(np.mean(tau_check**2, 0))
        self.min_delay = 0.5 * float(np.median(np.concatenate([np.diff(d.sample["t"]) for d in fit])))

    def index(self, groups):
        return (
            np.concatenate([np.arange(self.offset[g], self.offset[g] + self.k[g]) for g in groups])
            if groups
            else np.zeros(0, int)
        )

    def _system(self, transform, groups):
        """(G, b, yy) of the fit logs for `groups` (column order of index(groups)) with a model
        side time law (None: none), summed from the designs' cached normal equations."""
        idx = self.index(groups)
        if transform is None:
            return self.G[np.ix_(idx, idx)], self.b[idx], self.yy
        G, b, yy, _ = design_normal(self.fit[0], transform)
        for d in self.fit[1:]:
            Gd, bd, yyd, _ = design_normal(d, transform)
            G, b, yy = G + Gd, b + bd, yy + yyd
        return G[np.ix_(idx, idx)], b[idx], yy

    def fit_effects(self, effects):
        return fit_effects(self, effects)

    def solve(self, groups):
        """Constrained least squares on the fit logs for the union of `groups`.

        A time law (TIME_LAWS: pure delay or first-order lag of the model side) is a 1-D search
        on a DELAY_FINE_S grid around the linear estimate of the lag law (-d dtau_meas/dt, which
        only says where to look), extended while the best d sits at an end of the grid; only
        smooth model rows move, never the noisy measurement.
        Returns (params dict group -> array, fit SSE)."""
        timed = [g for g in groups if g in TIME_LAWS]
        if not timed:
            return self._solve_linear(groups, None)
        (time_group,) = timed
        law = TIME_LAWS[time_group]
        others = [g for g in groups if g != time_group]
        estimate = self._solve_linear(others + ["time_delay"], None, consistent=False)[0]["time_delay"][0]
        centre = DELAY_FINE_S * round(float(estimate) / DELAY_FINE_S)
        lowest = -MAX_DELAY_S if law == "shift" else DELAY_FINE_S  # a lag has d > 0
        errs = {}

        def scan(ds):
            for d in np.unique(np.clip(np.round(ds, 6), lowest, MAX_DELAY_S)):
                if float(d) not in errs:
                    errs[float(d)] = self._solve_linear(others, (law, float(d)), consistent=False)[1]

        steps = DELAY_FINE_S * np.arange(1, 7)
        scan(centre + np.r_[-steps[::-1], 0.0, steps])
        # The linear estimate only says where to look: walk on while the best is at an end.
        while True:
            grid = np.array(sorted(errs))
            best = min(errs, key=errs.get)
            if best == grid[-1] and best < MAX_DELAY_S:
                scan(best + steps)
            elif best == grid[0] and best > lowest:
                scan(best - steps)
            else:
                break
        # Between grid points: the vertex of the parabola through the best point and its
        # neighbours (SSE is smooth in d), kept when it fits better.
        i = int(np.searchsorted(grid, best))
        if 0 < i < len(grid) - 1:
            (d0, d1, d2) = grid[i - 1 : i + 2]
            e0, e1, e2 = errs[float(d0)], errs[float(d1)], errs[float(d2)]
            curvature = e0 - 2 * e1 + e2
            if curvature > 0:
                vertex = float(np.round(d1 + 0.5 * DELAY_FINE_S * (e0 - e2) / curvature, 3))  # 1 ms: reused
                errs[vertex] = self._solve_linear(others, (law, vertex), consistent=False)[1]
                best = min(errs, key=errs.get)
        params, err = self._solve_linear(others, (law, best))
        params = dict(params)
        params[time_group] = np.array([best])
        return {g: params[g] for g in groups}, err

    def _solve_linear(self, groups, transform, consistent=True):
        from scipy.optimize import lsq_linear

        G, b, yy = self._system(transform, groups)
        idx = self.index(groups)
        if len(idx) == 0:
            return {}, yy
        s = np.sqrt(np.diag(G))
        s[s <= 1e-12 * max(s.max(), 1e-300)] = 1.0
        Gs = G / np.outer(s, s)
        bs = b / s
        jitter = 1e-10 * np.trace(Gs) / len(idx)
        R = np.linalg.cholesky(Gs + jitter * np.eye(len(idx))).T
        z = np.linalg.solve(R.T, bs)
        lo, hi = [], []
        for g in groups:
            l, h = group_bounds(self.model, g, self.k[g])
            lo.append(l)
            hi.append(h)
        lo, hi = np.concatenate(lo) * s, np.concatenate(hi) * s
        if np.all(np.isinf(lo)) and np.all(np.isinf(hi)):
            ps = np.linalg.solve(R, z)
        else:
            ps = lsq_linear(R, z, bounds=(lo, hi), method="bvls", tol=1e-12).x
        p = ps / s
        if "payload" in groups and consistent:
            p = self._consistent_payload(groups, idx, p, R, z, s, lo, hi)
        sse = yy - 2 * p @ b + p @ G @ p
        out, pos = {}, 0
        for g in groups:
            out[g] = p[pos : pos + self.k[g]]
            pos += self.k[g]
        return out, max(float(sse), 0.0)

    def _consistent_payload(self, groups, idx, p, R, z, s, lo, hi):
        """Re-fit with theta_e0 + dtheta = P(eta) (log-Cholesky) when the linear fit is not
        physically consistent; other parameters keep their bounds."""
        from scipy.optimize import least_squares

        pos = 0
        for g in groups:
            if g == "payload":
                break
            pos += self.k[g]
        sl = slice(pos, pos + 10)
        theta_e0 = self.model.theta_e
        total = theta_e0 + p[sl]
        if p[sl][0] >= -1e-12 and inertial.is_physically_consistent(total, 1e-9):
            return p
        # Start: nominal end effector (plus a tiny sphere so the pseudo-inertia is invertible).
        start = theta_e0 + inertial.from_mass_com_inertia(1e-3, np.zeros(3), 1e-6 * np.eye(3))
        try:
            eta0 = inertial.theta_to_log_cholesky(start)
        except ValueError:
            eta0 = inertial.theta_to_log_cholesky(inertial.from_mass_com_inertia(1e-2, np.zeros(3), 1e-5 * np.eye(3)))
        others = np.ones(len(p), bool)
        others[sl] = False
        x0 = np.concatenate([eta0, np.clip(p[others] * s[others], lo[others], hi[others])])
        lo_x = np.concatenate([np.full(10, -np.inf), lo[others]])
        hi_x = np.concatenate([np.full(10, np.inf), hi[others]])
        eps = 1e-12
        x0 = np.clip(x0, lo_x + eps * (np.isfinite(lo_x)), hi_x - eps * (np.isfinite(hi_x)))

        def unpack(x):
            full = np.empty(len(p))
            full[sl] = (inertial.log_cholesky_to_theta(x[:10]) - theta_e0) * s[sl]
            full[others] = x[10:]
            return full

        def res(x):
            return R @ unpack(x) - z

        def jac(x):
            J = np.empty((len(z), len(x)))
            J[:, :10] = (R[:, sl] * s[sl]) @ inertial.log_cholesky_jacobian(x[:10])
            J[:, 10:] = R[:, others]
            return J

        with np.errstate(over="ignore", invalid="ignore"):
            sol = least_squares(res, x0, jac=jac, bounds=(lo_x, hi_x), method="trf", x_scale="jac", max_nfev=60)
        q = unpack(sol.x) / s
        if not np.all(np.isfinite(q)):  # solver failure: safe fallback, no payload change
            q = np.where(np.isfinite(q), q, 0.0)
            q[sl] = 0.0
        if q[sl][0] < 0:  # the payload must not remove mass: fall back to no payload change
            q[sl] = 0.0
        return q

    def check_residual(self, params, valid_only=True):
        """Check residual flattened row-major, on the valid (not speed-saturated) elements or on
        every element."""
        if not self.check:
            return np.zeros(0)
        r = np.concatenate([design_residual(d, params).reshape(-1) for d in self.check])
        return r[self.check_valid] if valid_only else r

    def check_residual_all(self, params):
        return self.check_residual(params, valid_only=False)

    def fit_residual(self, params):
        r = [design_residual(d, params).reshape(-1)[_flat_rows(d)[2]] for d in self.fit]
        return np.concatenate(r)


def fit_effects(problem, effects):
    """Best fit of a set of effects (Stribeck: the grid velocity with the lowest fit SSE)."""
    options = [[]]
    for e in effects:
        options = [o + [g] for o in options for g in effect_groups(e)]
    best = None
    for groups in options:
        params, sse = problem.solve(groups)
        if best is None or sse < best[1]:
            best = (params, sse)
    return best


def n_params(params):
    """Free parameters of a fit (of one fold's fit for inner folds: a tuple of dicts)."""
    if isinstance(params, tuple):
        return n_params(params[0]) if params else 0
    return sum(len(p) for p in params.values())


def noise_variance(r, block, joint):
    """White-noise variance from first differences in time inside blocks, per joint (smooth
    effects cancel), robust to sharp bursts (median absolute difference)."""
    out = []
    for j in np.unique(joint):
        m = joint == j
        d = np.diff(r[m])[block[m][1:] == block[m][:-1]]
        if len(d):
            out.append((1.4826 * np.median(np.abs(d))) ** 2 / 2)
    return float(np.mean(out)) if out else float(np.mean(r**2))


def resolvable(problem, params):
    """A delay shorter than half the logs' sample period is below what the logs resolve (and
    of the order of a simulator's own step): never reported as a cause (in any inner fold)."""
    if isinstance(params, tuple):
        return all(resolvable(problem, p) for p in params)
    d = _delay_of(params)
    return d is None or abs(d) >= problem.min_delay


def _delay_of(params):
    for g in TIME_LAWS:
        if g in params:
            return float(params[g][0])
    if "time_delay" in params:
        return float(params["time_delay"][0])
    return None


def significance(problem, r0, r1, sse0_fit, sse1_fit, k_added, joint=None):
    """The significance rule of the module docstring. r0/r1: held-out residual vectors of
    `problem` (validation residuals of the inner folds in the honest protocol).

    With c = r0 - r1 (the candidate's change of prediction), the held-out gain is
    sum(r0^2 - r1^2) = sum(2 r1 c + c^2); only 2 r1 c is random (r1 estimates the noise), so its
    standard error is taken from block sums of 2 r1 c (blocks absorb autocorrelation) and
    z = gain / se. Effects acting in short bursts (Stribeck at reversals) are then judged by
    how far each burst stands out of the noise, not by how many bursts a log happens to have."""
    sel = slice(None) if joint is None else (problem.check_joint == joint)
    r0, r1 = r0[sel], r1[sel]
    blocks = problem.check_block[sel]
    joints = problem.check_joint[sel]
    mse0 = float(np.mean(r0**2))
    gain = r0**2 - r1**2
    delta = float(np.mean(gain))
    cross = np.bincount(blocks, weights=2 * r1 * (r0 - r1))
    se = float(np.sqrt(np.sum(cross**2)))
    total = float(np.sum(gain))
    z = total / se if se > 0 else (np.inf if total > 1e-12 * max(np.sum(r0**2), 1e-300) else 0.0)
    p_blocks = _signed_rank_p(np.bincount(blocks, weights=gain)[np.bincount(blocks) > 0])
    sigma2 = noise_variance(r0, blocks, joints)
    change = r0 - r1
    relevance = max(
        float(np.sqrt(np.mean(change[joints == j] ** 2)) / max(problem.tau_rms_check[j], 1e-12))
        for j in np.unique(joints)
    )
    m = problem.n_fit_rows
    bic = m * np.log(max(sse1_fit, 1e-300) / max(sse0_fit, 1e-300)) + k_added * np.log(m)
    ok = bool(
        (z >= Z_BLOCK or p_blocks <= P_BLOCKS)
        and delta >= MIN_RELATIVE * mse0
        and delta >= MIN_NOISE_FRACTION * sigma2
        and relevance >= MIN_EFFECT_RATIO
        and (joint is not None or bic < 0)
    )
    return {
        "significant": ok,
        "z": float(z),
        "p_blocks": p_blocks,
        "delta_mse": delta,
        "relative": delta / mse0 if mse0 > 0 else 0.0,
        "noise_variance": sigma2,
        "bic_change": float(bic),
        "relevance": relevance,
    }


def _signed_rank_p(block_gain):
    """One-sided p of the Wilcoxon signed-rank test that block gains are positive (1 when there
    are fewer than MIN_BLOCKS blocks or no nonzero gain)."""
    from scipy.stats import wilcoxon

    g = block_gain[block_gain != 0]
    if len(block_gain) < MIN_BLOCKS or len(g) == 0:
        return 1.0
    return float(wilcoxon(g, alternative="greater").pvalue)


# ---- the diagnosis --------------------------------------------------------------------------
def choose_form(logs):
    return "inverse_dynamics" if all(l.a is not None for l in logs) else "momentum"


def regimes(designs, residuals):
    """Share of the squared residual per motion regime (per joint element) and per time window."""
    v = np.concatenate([d.features["v"] for d in designs])
    a = np.concatenate([d.features["a"] for d in designs])
    g = np.concatenate([d.features["g"] for d in designs])
    r2 = np.concatenate(residuals) ** 2
    total = r2.sum() or 1.0
    vmax = np.abs(v).max(0)
    near_zero = np.abs(v) < np.maximum(0.02, 0.05 * vmax)
    rev = np.zeros_like(near_zero)
    base = 0
    for d in designs:
        vv = d.features["v"]
        tt = d.row_time
        sign_change = np.zeros(vv.shape, bool)
        sign_change[1:] = np.sign(vv[1:]) * np.sign(vv[:-1]) < 0
        for j in range(vv.shape[1]):
            ts = tt[sign_change[:, j]]
            if len(ts):
                dist = np.min(np.abs(tt[:, None] - ts[None, :]), axis=1)
                rev[base : base + len(tt), j] = dist <= 0.1
        base += len(tt)
    masks = {
        "near_zero_velocity": near_zero,
        "reversal": rev,
        "high_acceleration": np.abs(a) >= np.quantile(np.abs(a), REGIME_QUANTILE, axis=0),
        "high_speed": np.abs(v) >= np.quantile(np.abs(v), REGIME_QUANTILE, axis=0),
        "high_gravity_load": np.abs(g) >= np.quantile(np.abs(g), REGIME_QUANTILE, axis=0),
        # Joint at its speed limit (velocity_saturation): the logged torque is not delivered.
        "velocity_saturation": np.concatenate([d.row_saturated for d in designs]),
    }
    share = {k: float(r2[m].sum() / total) for k, m in masks.items()}
    samples = {k: float(m.mean()) for k, m in masks.items()}
    windows = []
    base = 0
    for d, r in zip(designs, residuals):
        tt = d.row_time
        edges = np.arange(tt[0], tt[-1] + 1.0, 1.0)
        idx = np.digitize(tt, edges) - 1
        for w in np.unique(idx):
            sel = idx == w
            windows.append(
                {
                    "log": d.source,
                    "t_start": float(edges[w]),
                    "t_end": float(edges[w] + 1.0),
                    "share": float((r[sel] ** 2).sum() / total),
                }
            )
    windows.sort(key=lambda x: -x["share"])
    return share, samples, windows[:5]


def effect_params(model, effect, params, group_used):
    """Physical parameters of a fitted effect (JSON friendly)."""
    jp = model.joint_params
    p = params[group_used]
    lst = lambda x: [float(v) for v in np.atleast_1d(x)]  # noqa: E731
    if effect == "coulomb_friction":
        return {"delta_Fc_Nm": lst(p), "Fc_Nm": lst(jp.coulomb + p)}
    if effect == "viscous_friction":
        return {"delta_Fv_Nms_rad": lst(p), "Fv_Nms_rad": lst(jp.viscous + p)}
    if effect == "stribeck_friction":
        return {"Fs_Nm": lst(p), "vs_rad_s": float(group_used.split("@")[1])}
    if effect == "load_friction":
        return {"mu": lst(p)}
    if effect == "armature":
        return {"delta_Ia_kgm2": lst(p), "Ia_kgm2": lst(jp.armature + p)}
    if effect == "torque_offset":
        return {"offset_Nm": lst(p)}
    if effect == "torque_scale":
        return {"scale": lst(1.0 + p)}
    if effect == "payload":
        m = float(p[0])
        return {
            "theta_delta": lst(p),
            "theta_e": lst(model.theta_e + p),
            "mass_kg": m,
            "com_m": lst(p[1:4] / m) if m > 1e-9 else [0.0, 0.0, 0.0],
        }
    if effect == "time_delay":
        shift = group_used.endswith("@shift")
        return {
            "delay_s": float(p[0]),
            "law": "pure delay tau(t - d)" if shift else "first-order lag: tau_meas + d dtau_meas/dt = tau",
            "time_law": "shift" if shift else "lag",
        }
    if effect == "base_tilt":
        # Base rotated by RollPitchYaw(roll, pitch, 0): gravity in the base frame is
        # |g| [sin p, -cos p sin r, -cos p cos r] (real_arm's convention).
        gx, gy = float(p[0]), float(p[1])
        pitch = float(np.arcsin(np.clip(gx, -1, 1)))
        roll = float(-np.arcsin(np.clip(gy / max(np.cos(pitch), 1e-9), -1, 1)))
        return {"gravity_xy_over_g": [gx, gy], "roll_rad": roll, "pitch_rad": pitch}
    if effect == "joint_elasticity":
        return {"compliance_rad_per_Nm": lst(p), "stiffness_Nm_rad": [float(1 / c) if c > 1e-12 else None for c in p]}
    raise ValueError(effect)


def _group_of(effect, params):
    return next(g for g in params if g.split("@")[0] == effect)


@dataclass
class Diagnosis:
    result: dict  # diagnosis.json content
    form: str
    fit_designs: list
    check_designs: list
    check_residual_before: list  # per check log (R, n)
    check_residual_after: list
    combined_params: dict  # {group: array}, refitted on all fit logs
    corrected: dict  # corrected joint parameters and other effects for corrected_params.yaml
    corrected_model: object = None  # corrected_model.CorrectedModel (frozen selection + parameters)


# ---- the honest protocol: select on inner folds of the fit logs, score the check logs once --
class CrossValidated:
    """Selection data of the honest protocol: inner folds on the fit logs only. Each fold fits
    on its training designs and is scored on its validation designs; every fit-log element is
    validated exactly once, so the concatenated validation residuals carry the significance
    tests, the best single/pair, the greedy additions and the per-joint assignment. Parameters
    are one dict per fold (a tuple)."""

    def __init__(self, model, designs, folds, scheme):
        self.designs, self.folds, self.scheme = designs, folds, scheme
        self.problems = [Problem(model, [designs[i] for i in tr], [designs[i] for i in va]) for tr, va in folds]
        self.n = model.n
        self.empty = tuple({} for _ in folds)
        self.y_check = np.concatenate([p.y_check for p in self.problems])
        self.y_check_all = np.concatenate([p.y_check_all for p in self.problems])
        self.check_valid = np.concatenate([p.check_valid for p in self.problems])
        blocks, base = [], 0
        for p in self.problems:
            blocks.append(p.check_block + base)
            base += int(p.check_block.max()) + 1 if len(p.check_block) else 0
        self.check_block = np.concatenate(blocks)
        self.check_joint = np.concatenate([p.check_joint for p in self.problems])
        tau = np.concatenate([d.y + d.tau_hat_nominal for p in self.problems for d in p.check])
        self.tau_rms_check = np.sqrt(np.mean(tau**2, 0))
        self.n_fit_rows = sum(p.n_fit_rows for p in self.problems)
        self.yy = sum(p.yy for p in self.problems)
        self.min_delay = min(p.min_delay for p in self.problems)

    def fit_effects(self, effects):
        """Per-fold fits (tuple of params) and their summed training SSE."""
        fits = [fit_effects(p, effects) for p in self.problems]
        return tuple(f[0] for f in fits), float(sum(f[1] for f in fits))

    def check_residual(self, params, valid_only=True):
        """Validation residual of every fold, concatenated (flattened row-major)."""
        return np.concatenate([p.check_residual(q, valid_only) for p, q in zip(self.problems, params)])


TIME_FOLDS = 3  # inner folds (contiguous pieces in time) when there is a single fit log


def time_pieces(t, k=TIME_FOLDS):
    """k contiguous index slices of equal duration."""
    edges = np.searchsorted(t, t[0] + (t[-1] - t[0]) * np.arange(1, k) / k)
    bounds = np.concatenate([[0], edges, [len(t)]])
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def inner_folds(model, fit_logs, form, rule):
    """CrossValidated on the fit logs: leave one fit log out, or time-blocked folds (TIME_FOLDS
    contiguous pieces, leave one piece out) when there is one fit log."""
    masks = velocity_saturation(fit_logs, rule)
    if len(fit_logs) >= 2:
        designs = [build_design(model, l, form, WINDOW_S, saturated=m) for l, m in zip(fit_logs, masks)]
        scheme = "leave_one_fit_log_out"
    else:
        (log,), (mask,) = fit_logs, masks
        designs = []
        for sl in time_pieces(log.t):
            piece = dataclasses.replace(
                log.slice(sl), source=f"{log.source} [{log.t[sl][0]:.2f}, {log.t[sl][-1]:.2f}] s"
            )
            designs.append(build_design(model, piece, form, WINDOW_S, saturated=mask[sl]))
        scheme = "time_blocked"
    folds = [([i for i in range(len(designs)) if i != k], [k]) for k in range(len(designs))]
    return CrossValidated(model, designs, folds, scheme)


@dataclass
class Selection:
    effects: list  # selected, most important first
    params: object  # evaluator parameters of the selected set
    residual: np.ndarray  # evaluator residual (valid elements) after the selected set
    steps: list
    single: dict  # effect -> {params, sse, r, sig}: each effect alone
    joints: dict  # selected effect -> 1-based joints where it matters


def _drop(params, effect):
    """params without the groups of `effect` (per fold for inner folds)."""
    if isinstance(params, tuple):
        return tuple(_drop(p, effect) for p in params)
    return {g: v for g, v in params.items() if g.split("@")[0] != effect}


def select_effects(ev, effects, max_effects):
    """The selection of the module docstring on an evaluator `ev` (CrossValidated: validation
    residuals of inner folds of the fit logs; a Problem would select on its check logs)."""
    n = ev.n
    r0, sse0 = ev.y_check, ev.yy
    single = {}
    for e in effects:
        params, sse = ev.fit_effects([e])
        r1 = ev.check_residual(params)
        sig = significance(ev, r0, r1, sse0, sse, n_params(params))
        sig["significant"] &= resolvable(ev, params)
        single[e] = {"params": params, "sse": sse, "r": r1, "sig": sig}
    # The best pair (or single) first, exhaustively, then forward-greedy.
    selected, cur_params, cur_sse, cur_r, steps = _best_small_set(ev, effects, single, r0, sse0)
    while len(selected) < max_effects:
        best = None
        for e in effects:
            if e in selected:
                continue
            params, sse = ev.fit_effects(selected + [e])
            r1 = ev.check_residual(params)
            sig = significance(ev, cur_r, r1, cur_sse, sse, n_params(params) - n_params(cur_params))
            sig["significant"] &= resolvable(ev, params)
            if sig["significant"] and (best is None or sig["delta_mse"] > best[4]["delta_mse"]):
                best = (e, params, sse, r1, sig)
        if best is None:
            break
        e, cur_params, cur_sse, cur_r, sig = best
        selected.append(e)
        steps.append({"effect": e, "rms_after": _rms(cur_r), **sig})
    # Most important first: the validation loss when an effect is left out of the final set.
    if len(selected) > 1:
        loss = {}
        for e in selected:
            params, _ = ev.fit_effects([x for x in selected if x != e])
            loss[e] = float(np.mean(ev.check_residual(params) ** 2) - np.mean(cur_r**2))
        selected.sort(key=lambda e: -loss[e])
    # Joints where each selected effect matters: removing it from the combined fit on that
    # joint must lose a significant amount on the validation residuals.
    joints = {}
    for e in selected:
        r_wo = ev.check_residual(_drop(cur_params, e))
        if e in PER_JOINT:
            js = [j + 1 for j in range(n) if significance(ev, r_wo, cur_r, 1, 1, 0, joint=j)["significant"]]
        else:
            gain = np.array(
                [np.mean(r_wo[ev.check_joint == j] ** 2 - cur_r[ev.check_joint == j] ** 2) for j in range(n)]
            )
            js = [j + 1 for j in range(n) if gain[j] > MIN_RELATIVE * np.mean(r_wo[ev.check_joint == j] ** 2)]
        joints[e] = js or list(range(1, n + 1))
    return Selection(selected, cur_params, cur_r, steps, single, joints)


def _best_small_set(ev, effects, single, r0, sse0_fit):
    """Exhaustive search over sets of one or two effects (greedy alone can pick one effect
    that mimics two, e.g. a torque scale for armature + delay on an arm with large nominal
    armature, or miss two effects that only fit together, e.g. payload + base tilt, both
    gravity-like). A set is admissible when each member is significant against the set without
    it; the admissible set with the lowest validation residual wins."""
    fits = {(): (ev.empty, sse0_fit, r0)}
    for e in effects:
        fits[(e,)] = (single[e]["params"], single[e]["sse"], single[e]["r"])
    admissible = [()] + [(e,) for e in effects if single[e]["sig"]["significant"]]
    for i, e in enumerate(effects):
        for f in effects[i + 1 :]:
            params, sse = ev.fit_effects([e, f])
            r = ev.check_residual(params)
            fits[(e, f)] = (params, sse, r)
            ok = resolvable(ev, params)
            for keep in (e, f):
                p0, s0, rr0 = fits[(keep,)]
                ok = ok and significance(ev, rr0, r, s0, sse, n_params(params) - n_params(p0))["significant"]
            if ok:
                admissible.append((e, f))
    best = min(admissible, key=lambda k: float(np.mean(fits[k][2] ** 2)))
    params, sse, r = fits[best]
    steps = []
    prev = ()
    order = sorted(best, key=lambda e: float(np.mean(fits[(e,)][2] ** 2)))
    for e in order:
        cur = tuple(sorted((x for x in best if x in prev + (e,)), key=best.index))
        p1, s1, r1 = fits[cur]
        p0, s0, rr0 = fits[prev]
        sig = significance(ev, rr0, r1, s0, s1, n_params(p1) - n_params(p0))
        steps.append({"effect": e, "rms_after": _rms(r1), "phase": "best pair", **sig})
        prev = cur
    return list(order), params, sse, r, steps


# ---- frozen scoring: the one code path for check logs and for a corrected_model.yaml ---------
WINDOW_S = 0.1  # momentum-form window


def frozen_designs(model, logs, form, rule, window_s=WINDOW_S):
    """Designs of logs scored with a frozen rule: the residual form of the diagnosis (the
    momentum form when a log has no accelerations) and the speed-saturation rule of the fit
    logs (None: nothing flagged)."""
    if form == "inverse_dynamics" and any(l.a is None for l in logs):
        form = "momentum"
    masks = velocity_saturation(logs, rule) if rule is not None else [np.zeros(l.v.shape, bool) for l in logs]
    return [build_design(model, l, form, window_s, saturated=m) for l, m in zip(logs, masks)]


def score_designs(corrected, designs):
    """(before, after): residual (R, n) per design of the nominal model and of the frozen
    corrected model (corrected_model.CorrectedModel). Fits nothing."""
    from .corrected_model import CorrectedModelError, group_params

    params = group_params(corrected.effects)
    for k, e in enumerate(corrected.effects):
        if e.name == "stribeck_friction" and f"stribeck_friction@{float(e.params['vs_rad_s'])}" not in designs[0].cols:
            raise CorrectedModelError(
                f"{corrected.path or 'corrected model'}: effects[{k}].params.vs_rad_s: "
                f"{e.params['vs_rad_s']} is not one of {', '.join(map(str, STRIBECK_VELOCITIES))}"
            )
    return [d.y for d in designs], [design_residual(d, params) for d in designs]


def score(model, corrected, logs):
    """Score a frozen corrected model on logs (`diagnose --model corrected_model.yaml --check`):
    (designs, before, after, held_out_numbers)."""
    sc = corrected.scoring
    designs = frozen_designs(model, logs, sc.residual_form, sc.saturation, sc.window_s)
    before, after = score_designs(corrected, designs)
    return designs, before, after, held_out_numbers(designs, before, after)


def _rms_table(before, after, mask):
    """RMS before/after and reduction, overall and per joint, over the elements in `mask`."""
    n = before.shape[1]
    b = [_rms(before[mask[:, j], j]) if mask[:, j].any() else 0.0 for j in range(n)]
    a = [_rms(after[mask[:, j], j]) if mask[:, j].any() else 0.0 for j in range(n)]
    rb, ra = (_rms(before[mask]), _rms(after[mask])) if mask.any() else (0.0, 0.0)
    return {
        "rms_before": rb,
        "rms_after": ra,
        "reduction": _reduction(rb, ra),
        "rms_before_per_joint": b,
        "rms_after_per_joint": a,
        "reduction_per_joint": [_reduction(x, y) for x, y in zip(b, a)],
    }


def held_out_numbers(designs, before, after):
    """Residual RMS before/after on scored logs: every element (contract meaning) and without
    the speed-saturated ones, overall, per joint and per log."""
    b, a = np.concatenate(before), np.concatenate(after)
    valid = ~np.concatenate([d.row_saturated for d in designs])
    out = _rms_table(b, a, np.ones_like(valid))
    out["without_saturated"] = _rms_table(b, a, valid)
    out["logs"] = [d.source for d in designs]
    out["rms_before_per_log"] = [_rms(x) for x in before]
    out["rms_after_per_log"] = [_rms(x) for x in after]
    out["residual_form"] = designs[0].form
    return out


def corrected_model_of(model, selection, params, form, rule, model_path="", fit_sources=()):
    """CorrectedModel of a diagnosis: the starting model, the selected effects (most important
    first) with their parameters refitted on all fit logs, and the frozen scoring rule."""
    from .corrected_model import CorrectedEffect, CorrectedModel, Scoring

    path = str(model_path or model.source or "")
    effects = [
        CorrectedEffect(e, list(selection.joints[e]), effect_params(model, e, params, _group_of(e, params)))
        for e in selection.effects
    ]
    return CorrectedModel(
        path,
        effects,
        Scoring(form, WINDOW_S, rule),
        str(Path(path).resolve()) if path else "",
        [str(s) for s in fit_sources],
    )


def diagnose(model, fit_logs, check_logs, effects=EFFECTS, form=None, max_effects=6, model_path=""):
    """Diagnose the gap between `model` and logs; returns a Diagnosis (result = contract JSON).

    Honest protocol: every selection step and threshold uses the fit logs only (inner folds:
    leave one fit log out, time-blocked with one fit log); the parameters of the selected set
    are refitted on all fit logs and the check logs are scored once with them (`test`)."""
    with single_threaded_blas():
        return _diagnose(model, list(fit_logs), list(check_logs), effects, form, max_effects, model_path)


def _diagnose(model, fit_logs, check_logs, effects, form, max_effects, model_path):
    form = form or choose_form(fit_logs + check_logs)
    rule = saturation_rule(fit_logs)  # frozen on the fit logs
    cv = inner_folds(model, fit_logs, form, rule)
    sel = select_effects(cv, effects, max_effects)
    check = frozen_designs(model, check_logs, form, rule)
    final = Problem(model, cv.designs, check)
    params, _ = final.fit_effects(sel.effects)
    corrected_model = corrected_model_of(model, sel, params, form, rule, model_path, [l.source for l in fit_logs])
    before, after = score_designs(corrected_model, check)
    test = held_out_numbers(check, before, after)
    n = model.n
    entries = []
    for e in effects:
        alone, _ = final.fit_effects([e])
        rms_alone = _rms(final.check_residual_all(alone))
        chosen = e in sel.effects
        src = params if chosen else alone
        entry = {
            "name": e,
            "joints": sel.joints[e] if chosen else _effect_joints_single(cv, sel.single[e]["params"], e, n),
            "params": effect_params(model, e, src, _group_of(e, src)),
            "rms_check_after": rms_alone,
            "reduction": _reduction(test["rms_before"], rms_alone),
            "significant": chosen,
            "params_from": "combined" if chosen else "alone",
            "test_alone": _json_sig(sel.single[e]["sig"]),
        }
        if chosen:
            entry["selection_step"] = sel.effects.index(e) + 1
        entries.append(entry)
    entries.sort(key=lambda x: (not x["significant"], x.get("selection_step", 0), -x["test_alone"]["delta_mse"]))

    cv_before = cv.y_check_all.reshape(-1, n)
    cv_after = cv.check_residual(sel.params, valid_only=False).reshape(-1, n)
    cv_valid = cv.check_valid.reshape(-1, n)
    cross_validation = {
        "scheme": cv.scheme,
        "folds": [{"fit": [d.source for d in p.fit], "validate": [d.source for d in p.check]} for p in cv.problems],
        **_rms_table(cv_before, cv_after, np.ones_like(cv_valid)),
        "without_saturated": _rms_table(cv_before, cv_after, cv_valid),
        "selection": sel.steps,
    }
    result = _held_out_result(check, before, after, test, entries, form)
    result["gap"]["rms_fit"] = float(np.sqrt(final.yy / max(final.n_fit_rows, 1)))
    result["combined"].update(rms_fit_after=_rms(final.fit_residual(params)), selection=sel.steps)
    result.update(
        {
            "test": {
                **test,
                "note": "check logs, scored once with the frozen selection and parameters; "
                "no selection step or threshold saw them",
            },
            "cross_validation": cross_validation,
            "protocol": {
                "selection_data": "fit logs only (inner cross-validation: " + cv.scheme + ")",
                "check_logs": "scored once (test)",
                "saturation_top_speed_rad_s": list(rule.top_speed_rad_s),
            },
            "significance_rule": {
                "z_block": Z_BLOCK,
                "p_blocks": P_BLOCKS,
                "min_blocks": MIN_BLOCKS,
                "block_s": BLOCK_S,
                "min_relative": MIN_RELATIVE,
                "min_effect_ratio": MIN_EFFECT_RATIO,
                "min_noise_fraction": MIN_NOISE_FRACTION,
                "information_criterion": "BIC on the inner training folds",
                "data": "validation residuals of the inner folds on the fit logs",
            },
        }
    )
    corrected = corrected_parameters(model, sel.effects, params)
    return Diagnosis(result, form, cv.designs, check, before, after, params, corrected, corrected_model)


def _held_out_result(designs, before, after, test, entries, form):
    """The contract fields of diagnosis.json (gap, effects, cause, combined) on scored logs."""
    named = [e["name"] for e in entries if e["significant"]]
    share, samples, windows = regimes(designs, before)
    return {
        "gap": {
            "rms_check": test["rms_before"],
            "rms_check_per_joint": test["rms_before_per_joint"],
            "where": {
                "joints": [int(j) + 1 for j in np.argsort(-np.array(test["rms_before_per_joint"]))],
                "regimes": share,
                "regime_sample_share": samples,
                "time_windows": windows,
            },
            "residual_form": form,
            "rms_check_per_log": test["rms_before_per_log"],
            "velocity_saturation": _saturation_summary(designs, before),
        },
        "effects": entries,
        "cause": named,
        "combined": {
            "effects": named,
            "rms_check_after": test["rms_after"],
            "reduction": test["reduction"],
            "rms_check_per_joint_after": test["rms_after_per_joint"],
            "rms_check_per_log_after": test["rms_after_per_log"],
            "regimes_after": regimes(designs, after)[0],
            "without_saturated": {
                "rms_check": test["without_saturated"]["rms_before"],
                "rms_check_after": test["without_saturated"]["rms_after"],
                "reduction": test["without_saturated"]["reduction"],
            },
        },
    }


def frozen_diagnosis(model, corrected, logs):
    """Logs scored with a frozen corrected model (`diagnose --model corrected_model.yaml
    --check`): the contract fields on those logs, each effect's own numbers with that effect of
    the file alone; nothing is fitted or selected."""
    from .corrected_model import group_params

    with single_threaded_blas():
        designs, before, after, test = score(model, corrected, logs)
        entries = []
        for k, e in enumerate(corrected.effects):
            rms = _rms(np.concatenate([design_residual(d, group_params([e])) for d in designs]))
            entries.append(
                {
                    "name": e.name,
                    "joints": list(e.joints),
                    "params": e.params,
                    "rms_check_after": rms,
                    "reduction": _reduction(test["rms_before"], rms),
                    "significant": True,
                    "params_from": "frozen",
                    "selection_step": k + 1,
                }
            )
        result = _held_out_result(designs, before, after, test, entries, designs[0].form)
    sc = corrected.scoring
    result["gap"]["rms_fit"] = None  # no fit logs
    result["test"] = {**test, "note": "scored with the frozen corrected model; nothing fitted, nothing selected"}
    result["frozen"] = {
        "corrected_model": corrected.path,
        "model": str(corrected.model_path()),
        "fitted": "nothing",
        "residual_form": sc.residual_form,
        "saturation_top_speed_rad_s": sc.saturation.top_speed_rad_s if sc.saturation else None,
    }
    return Diagnosis(
        result, designs[0].form, [], designs, before, after, group_params(corrected.effects), {}, corrected
    )


def leave_one_out(model, logs, **kwargs):
    """Each log held out once, the effects selected and fitted on the others (nested: the
    held-out log is never seen by the inner selection): (fold Diagnoses, pooled)."""
    import time

    folds = []
    for held in range(len(logs)):
        t0 = time.perf_counter()
        folds.append(diagnose(model, [l for k, l in enumerate(logs) if k != held], [logs[held]], **kwargs))
        folds[-1].result["wall_time_s"] = time.perf_counter() - t0
    return folds, pool_held_out(folds)


def pool_held_out(folds):
    """Held-out (test) numbers over folds that each check one log: RMS before/after pooled over
    all held-out samples (per joint and overall, all samples and without speed-saturated ones),
    the mean over folds (a per-run reduction), per fold, and the effects named in every fold."""
    before = np.concatenate([r for d in folds for r in d.check_residual_before])
    after = np.concatenate([r for d in folds for r in d.check_residual_after])
    valid = ~np.concatenate([c.row_saturated for d in folds for c in d.check_designs])
    per_fold = [
        {
            "check": [c.source for c in d.check_designs],
            "rms_before": d.result["gap"]["rms_check"],
            "rms_after": d.result["combined"]["rms_check_after"],
            "reduction": d.result["combined"]["reduction"],
            "without_saturated": d.result["combined"]["without_saturated"],
            "cause": d.result["cause"],
            "params": {e["name"]: e["params"] for e in d.result["effects"] if e["significant"]},
            "rms_before_per_joint": d.result["gap"]["rms_check_per_joint"],
            "rms_after_per_joint": d.result["combined"]["rms_check_per_joint_after"],
            "cross_validation": {
                k: d.result["cross_validation"][k] for k in ("scheme", "rms_before", "rms_after", "reduction")
            },
            "wall_time_s": d.result.get("wall_time_s"),
        }
        for d in folds
    ]
    mean_before = float(np.mean([f["rms_before"] for f in per_fold]))
    mean_after = float(np.mean([f["rms_after"] for f in per_fold]))
    causes = [set(f["cause"]) for f in per_fold]
    order = [e for f in per_fold for e in f["cause"]]
    every = set.intersection(*causes) if causes else set()
    some = set.union(*causes) if causes else set()
    return {
        "protocol": "nested: each held-out log scored once; selection on inner folds of the other logs",
        "pooled": _rms_table(before, after, np.ones_like(valid)),
        "pooled_unsaturated": _rms_table(before, after, valid),
        "saturated_share": float(1.0 - valid.mean()),
        "mean_over_folds": {
            "rms_before": mean_before,
            "rms_after": mean_after,
            "reduction": _reduction(mean_before, mean_after),
        },
        "folds": per_fold,
        "named_in_every_fold": sorted(every, key=order.index),
        "named_in_some_fold": sorted(some - every, key=order.index),
    }


def _saturation_summary(designs, residuals):
    """Where joints ran at their speed limit in the check logs and the residual share there."""
    sat = np.concatenate([d.row_saturated for d in designs])
    r2 = np.concatenate(residuals) ** 2
    spans = []
    for d in designs:
        for j in range(sat.shape[1]):
            m = np.concatenate([[False], d.row_saturated[:, j], [False]]).astype(int)
            for i0, i1 in zip(np.flatnonzero(np.diff(m) == 1), np.flatnonzero(np.diff(m) == -1) - 1):
                spans.append(
                    {
                        "log": d.source,
                        "joint": j + 1,
                        "t_start": float(d.row_time[i0]),
                        "t_end": float(d.row_time[i1]),
                        "speed_rad_s": float(np.abs(d.features["v"][i0 : i1 + 1, j]).mean()),
                    }
                )
    return {
        "element_share": float(sat.mean()),
        "per_joint_share": [float(x) for x in sat.mean(0)],
        "residual_share": float(r2[sat].sum() / (r2.sum() or 1.0)),
        "spans": spans,
    }


def _reduction(before, after):
    return float(np.clip(1.0 - after / before, 0.0, 1.0)) if before > 0 else 0.0


def _json_sig(sig):
    return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in sig.items()}


def _effect_joints_single(ev, params, e, n):
    """Joints an insignificant effect would touch most (for information only; validation data)."""
    r0 = ev.y_check
    r1 = ev.check_residual(params)
    gain = np.array([np.mean(r0[ev.check_joint == j] ** 2 - r1[ev.check_joint == j] ** 2) for j in range(n)])
    return [int(j) + 1 for j in np.argsort(-gain)[:3] if gain[j] > 0]


def corrected_parameters(model, selected, params):
    """Corrected joint parameters (models/*_params.yaml `joints` format) plus the other effects."""
    jp = model.joint_params
    fric = {
        "coulomb_Nm": jp.coulomb.copy(),
        "viscous_Nms_rad": jp.viscous.copy(),
        "armature_kgm2": jp.armature.copy(),
        "offset_Nm": jp.offset.copy(),
    }
    other = {}
    plant_effects = {}
    for e in selected:
        g = _group_of(e, params)
        p = params[g]
        if e == "coulomb_friction":
            fric["coulomb_Nm"] = jp.coulomb + p
        elif e == "viscous_friction":
            fric["viscous_Nms_rad"] = jp.viscous + p
        elif e == "armature":
            fric["armature_kgm2"] = jp.armature + p
        elif e == "torque_offset":  # same term as the model's beta (tau = ... + beta)
            fric["offset_Nm"] = jp.offset + p
            plant_effects["torque_sensor_offset_Nm"] = [float(x) for x in p]
        else:
            other[e] = effect_params(model, e, params, g)
            if e == "torque_scale":
                plant_effects["torque_sensor_scale"] = other[e]["scale"]
            elif e == "time_delay" and g == "time_delay@lag":
                plant_effects["torque_sensor_lag_s"] = other[e]["delay_s"]  # a filtered torque signal
            elif e == "time_delay" and other[e]["delay_s"] < 0:
                # real_arm's time_delay_s is an actuation delay (torque leads motion); a pure
                # measurement delay (d > 0) has no plant counterpart and stays in `other`.
                plant_effects["time_delay_s"] = -other[e]["delay_s"]
            elif e == "base_tilt":
                plant_effects["base_tilt_rad"] = [other[e]["roll_rad"], other[e]["pitch_rad"]]
            elif e == "joint_elasticity":
                plant_effects["joint_stiffness_Nm_rad"] = [
                    s if s is not None else 1e12 for s in other[e]["stiffness_Nm_rad"]
                ]
    return {
        "friction": {k: [float(x) for x in v] for k, v in fric.items()},
        "other": other,
        "plant_effects": plant_effects,
    }
