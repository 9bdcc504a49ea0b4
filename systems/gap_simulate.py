"""Withheld-effect logs for the diagnosis self-check (`safesysid diagnose --self-check`).

How a log is made (fast and deterministic given the seed):
  * trajectory: per joint a sum of three sines (0.1..0.7 Hz, random phases) about a random centre
    inside the joint limits, amplitudes scaled so |v| <= 0.8 of the velocity limit; sampled at
    100 Hz with one 0.5 s gap (samples removed), like the real logs;
  * torque: the RobotModel's exact inverse dynamics (same regressor as the diagnoser's nominal)
    with the withheld effects applied in their physical form, not in the diagnoser's linearised
    columns: delay evaluates the dynamics at t - d (or, in half the delay cases, the logged torque
    is a first-order lag of the torque, d tau_meas' + tau_meas = tau, as the real Gen3 logs'
    filtered torque signal), base tilt rotates the gravity vector, joint
    elasticity logs the motor-side angle q_link + tau / k, payload changes the end-effector
    inertia (physically consistent), scale and offset act on the torque sensor;
  * noise: bounded uniform on the torque, +-level * (torque range of the joint), level drawn in
    [0.5 %, 3 %].
Effect sizes are drawn as a signal-to-noise ratio: the effect's torque RMS on the joints it
acts on is SNR times the noise RMS there (SNR in [1, 4]; every third non-null case close to the
noise floor, SNR in [1, 1.3]), capped by physical limits; when a
cap keeps an effect below 0.8x the noise RMS the joints are redrawn (up to 10 times), so every
case is inside the range the check is about. Caps: delay <= 50 ms, lag <= 150 ms, tilt <= 0.05 rad,
compliance <= 0.003 rad/(N m), load friction mu <= 0.3, scale within +-15 %, payload <= 5 kg,
Coulomb / Stribeck / viscous / armature / offset increments <= 10 N m / 20 N m / 30 N m s/rad /
5 kg m^2 / 10 N m. Logs are written with or without the acceleration columns. Every other
two-effect case puts two per-joint effects on the same joints.

Honest like the diagnosis: each case has two fit logs, on which all selection happens (inner
cross-validation), and one check log, scored once. Named effects are compared with the truth by
name (confusion table) and by value (value_errors: delay, friction, armature, offset, payload
mass and CoM, tilt, stiffness). detection_limits finds, per effect, the smallest physical size
named in >= 90 % of cases at a given noise level.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import inertial
from .gap import EFFECTS, PER_JOINT, first_order_lag, segments

RATE_HZ = 100.0
GAP_S = 0.5
SNR_RANGE = (1.0, 4.0)
NOISE_LEVEL_RANGE = (0.005, 0.03)
STRIBECK_VS = (0.03, 0.05, 0.08, 0.15)
MAX_DRAWS = 10
MIN_SNR_AFTER_CAP = 0.8


@dataclasses.dataclass
class Trajectory:
    centre: np.ndarray
    amp: np.ndarray  # (3, n)
    omega: np.ndarray  # (3, n)
    phase: np.ndarray  # (3, n)

    def __call__(self, t):
        t = np.asarray(t, float)[:, None, None]
        arg = self.omega * t + self.phase
        q = self.centre + np.sum(self.amp * np.sin(arg), 1)
        v = np.sum(self.amp * self.omega * np.cos(arg), 1)
        a = -np.sum(self.amp * self.omega**2 * np.sin(arg), 1)
        return q, v, a


def random_trajectory(model, rng):
    jp = model.joint_params
    n = model.n
    lo = np.where(np.isfinite(jp.position_lower) & (jp.position_lower > -1e3), jp.position_lower, -np.pi)
    hi = np.where(np.isfinite(jp.position_upper) & (jp.position_upper < 1e3), jp.position_upper, np.pi)
    half = 0.5 * (hi - lo)
    centre = 0.5 * (lo + hi) + rng.uniform(-0.3, 0.3, n) * half
    room = 0.85 * (half - np.abs(centre - 0.5 * (lo + hi)))
    omega = 2 * np.pi * rng.uniform(0.1, 0.7, (3, n))
    amp = rng.uniform(0.3, 1.0, (3, n))
    amp *= np.minimum(1.0, room / amp.sum(0))
    vlim = np.where(np.isfinite(jp.velocity_limit) & (jp.velocity_limit > 0), jp.velocity_limit, 1.5)
    vmax = (amp * omega).sum(0)
    amp *= np.minimum(1.0, 0.8 * vlim / vmax)
    return Trajectory(centre, amp, omega, rng.uniform(0, 2 * np.pi, (3, n)))


def sample_times(rng, duration_s):
    t = np.arange(0.0, duration_s, 1.0 / RATE_HZ)
    t = t + rng.uniform(-0.1, 0.1, len(t)) / RATE_HZ  # timing jitter, still increasing
    g0 = rng.uniform(0.3, 0.7) * duration_s
    return t[(t < g0) | (t > g0 + GAP_S)]


# ---- effects in their physical form ---------------------------------------------------------
def _tilted_model(model, roll, pitch):
    g = np.linalg.norm(model.tree.gravity)
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    # Gravity in the base frame for a base rotated by RollPitchYaw(roll, pitch, 0) (real_arm).
    gb = g * np.array([sp, -cp * sr, -cp * cr])
    return dataclasses.replace(model, tree=dataclasses.replace(model.tree, gravity=gb))


def payload_theta(model, mass, rng):
    """A solid cylinder held near the grasp point (end-effector frame), physically consistent."""
    c = model.extra.get("grasp_point", np.zeros(3)) + rng.uniform(-0.05, 0.05, 3)
    r, h = 0.04, 0.15
    i_c = mass * np.diag([(3 * r * r + h * h) / 12, (3 * r * r + h * h) / 12, r * r / 2])
    return inertial.from_mass_com_inertia(mass, c, i_c)


def true_torque(model, traj, t, effects):
    """Joint torque the 'real' arm measures (before noise) and the logged q offset."""
    timing = effects.get("time_delay", {})
    lag = timing.get("delay_s", 0.0) if timing.get("law") == "lag" else 0.0
    q, v, a = traj(t - (0.0 if lag else timing.get("delay_s", 0.0)))
    m = model
    if "base_tilt" in effects:
        m = _tilted_model(m, *effects["base_tilt"]["roll_pitch_rad"])
    if "payload" in effects:
        m = m.with_end_effector_theta(m.theta_e + effects["payload"]["theta"])
    tau = m.inverse_dynamics(q, v, a)
    jp = model.joint_params
    transmitted = tau - (jp.coulomb * np.sign(v) + jp.viscous * v + jp.offset)  # link-side torque
    e = effects
    if "coulomb_friction" in e:
        tau = tau + e["coulomb_friction"]["delta"] * np.sign(v)
    if "viscous_friction" in e:
        tau = tau + e["viscous_friction"]["delta"] * v
    if "stribeck_friction" in e:
        s = e["stribeck_friction"]
        tau = tau + s["delta"] * np.sign(v) * np.exp(-((v / s["vs"]) ** 2))
    if "armature" in e:
        tau = tau + e["armature"]["delta"] * a
    if "load_friction" in e:
        # tau = tau0 + mu |tau| sgn(v), solved exactly (tau keeps the sign of tau0 for mu < 1).
        tau = tau / (1.0 - e["load_friction"]["mu"] * np.sign(v) * np.sign(tau))
    # Sensor: scale and offset on the measured torque.
    if "torque_scale" in e:
        tau = tau * e["torque_scale"]["scale"]
    if "torque_offset" in e:
        tau = tau + e["torque_offset"]["delta"]
    if lag:  # the logged torque signal is low-passed (steady at each segment start)
        tau = first_order_lag(t, tau, np.array(segments(t)), lag)
    q_log, v_log, a_log = traj(t)
    if "joint_elasticity" in e:
        # Encoders on the motor side: logged angle = link angle + deflection tau_s / k.
        q_log = q_log + transmitted * e["joint_elasticity"]["compliance"]
    return q_log, v_log, a_log, tau


def _unit_effect(name, model, rng, joints):
    """Effect at a reference magnitude (scaled to the target SNR afterwards) and its cap."""
    n = model.n
    mask = np.zeros(n)
    mask[joints] = 1.0
    sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    if name == "coulomb_friction":
        return {"delta": mask * rng.uniform(0.5, 1.5, n)}, 10.0
    if name == "viscous_friction":
        return {"delta": mask * rng.uniform(0.5, 1.5, n)}, 30.0
    if name == "stribeck_friction":
        return {"delta": mask * rng.uniform(0.5, 1.5, n), "vs": float(rng.choice(STRIBECK_VS))}, 20.0
    if name == "armature":
        return {"delta": mask * rng.uniform(0.5, 1.5, n)}, 5.0
    if name == "load_friction":
        return {"mu": mask * rng.uniform(0.5, 1.5, n) * 0.03}, 0.3
    if name == "torque_offset":
        return {"delta": mask * sign * rng.uniform(0.5, 1.5, n)}, 10.0
    if name == "torque_scale":
        return {"scale": 1.0 + mask * sign * rng.uniform(0.02, 0.04, n)}, 0.15
    if name == "payload":
        return {"mass_kg": 1.0, "theta": payload_theta(model, 1.0, rng)}, 5.0
    if name == "time_delay":  # a pure delay or a first-order lag of the torque signal
        return ({"delay_s": 0.01, "law": "lag"}, 0.15) if rng.random() < 0.5 else ({"delay_s": 0.01}, 0.05)
    if name == "base_tilt":
        ang = rng.uniform(-1, 1, 2)
        return {"roll_pitch_rad": 0.01 * ang / np.abs(ang).max()}, 0.05
    if name == "joint_elasticity":
        return {"compliance": mask * rng.uniform(0.5, 1.5, n) * 1e-3}, 0.003
    raise ValueError(name)


def _scale_effect(name, eff, factor, cap):
    """Multiply the effect magnitude by `factor` (capped)."""
    e = dict(eff)
    if name == "torque_scale":
        dev = (e["scale"] - 1.0) * factor
        e["scale"] = 1.0 + np.clip(dev, -cap, cap)
    elif name == "payload":
        m = min(e["mass_kg"] * factor, cap)
        e["theta"] = e["theta"] * (m / e["mass_kg"])
        e["mass_kg"] = m
    elif name == "time_delay":
        e["delay_s"] = float(min(e["delay_s"] * factor, cap))
    elif name == "base_tilt":
        v = np.asarray(e["roll_pitch_rad"]) * factor
        e["roll_pitch_rad"] = v * min(1.0, cap / np.abs(v).max())
    elif name == "joint_elasticity":
        e["compliance"] = np.minimum(e["compliance"] * factor, cap)
    elif name == "load_friction":
        e["mu"] = np.minimum(e["mu"] * factor, cap)
    else:
        d = e["delta"] * factor
        e["delta"] = np.clip(d, -cap, cap)
    return e


def _effect_rms(model, name, eff, trajs, times, clean):
    """Per-joint RMS of what the effect changes in the residual of the nominal model."""
    if name == "joint_elasticity":  # acts through the logged angle: the nominal model sees it there
        contrib = [
            model.inverse_dynamics(*true_torque(model, tr, t, {name: eff})[:3]) - c[3]
            for tr, t, c in zip(trajs, times, clean)
        ]
    else:
        contrib = [true_torque(model, tr, t, {name: eff})[3] - c[3] for tr, t, c in zip(trajs, times, clean)]
    return np.sqrt(np.mean(np.concatenate(contrib) ** 2, 0))


def make_case(
    model,
    rng,
    injected,
    with_acceleration,
    n_fit=2,
    n_check=1,
    duration_s=10.0,
    snr_range=SNR_RANGE,
    same_joints=False,
    fixed=None,
    noise_level=None,
):
    """Fit and check logs with the `injected` effects withheld from `model`.

    Effect sizes are drawn as an SNR in `snr_range` (module docstring) unless `fixed` gives an
    effect in its physical form ({name: effect}, e.g. from effect_at: detection limits).
    same_joints: every per-joint effect acts on the joints of the first one (two effects on the
    same joint). noise_level: fraction of each joint's torque range (default: drawn).
    Returns (fit_logs, check_logs, truth) where truth records every effect's parameters, the
    achieved SNR, the joints it acts on and the joints it was injected on (1-based)."""
    from safesysid.joint_log import JointLog

    n = model.n
    trajs = [random_trajectory(model, rng) for _ in range(n_fit + n_check)]
    times = [sample_times(rng, duration_s) for _ in trajs]
    clean = [true_torque(model, tr, t, {}) for tr, t in zip(trajs, times)]
    tau_all = np.concatenate([c[3] for c in clean])
    level = rng.uniform(*NOISE_LEVEL_RANGE) if noise_level is None else float(noise_level)
    noise_amp = level * (tau_all.max(0) - tau_all.min(0))
    noise_rms = noise_amp / np.sqrt(3.0)
    effects, truth = {}, {}
    shared = None  # joints of the first per-joint effect (same_joints)
    for name in injected:
        snr = rng.uniform(*snr_range)
        for _attempt in range(MAX_DRAWS):
            # Joints and shape are redrawn when the physical cap keeps the effect far below the
            # drawn SNR (e.g. a stiff joint on an axis whose torque hardly depends on its angle).
            if name not in PER_JOINT:
                joints = np.arange(n)
            elif same_joints and shared is not None:
                joints = shared
            else:
                joints = np.sort(rng.choice(n, size=rng.integers(1, 4), replace=False))
            if fixed and name in fixed:
                eff = fixed[name]
                joints = np.flatnonzero(_joint_mask(name, eff, n)) if name in PER_JOINT else joints
            else:
                eff, cap = _unit_effect(name, model, rng, joints)
            rms = _effect_rms(model, name, eff, trajs, times, clean)
            acts = rms >= 0.2 * rms.max() if rms.max() > 0 else np.zeros(n, bool)
            noise_acts = np.sqrt(np.mean(noise_rms[acts] ** 2)) if acts.any() else 1.0
            achieved = np.sqrt(np.mean(rms[acts] ** 2)) if acts.any() else 0.0
            if fixed and name in fixed:
                final = achieved
                break
            eff = _scale_effect(name, eff, snr * noise_acts / achieved if achieved > 0 else 1.0, cap)
            final = (
                np.sqrt(np.mean(_effect_rms(model, name, eff, trajs, times, clean)[acts] ** 2)) if acts.any() else 0.0
            )
            if final >= MIN_SNR_AFTER_CAP * noise_acts:
                break
        if name in PER_JOINT and shared is None:
            shared = joints
        effects[name] = eff
        truth[name] = {
            "joints": [int(j) + 1 for j in np.flatnonzero(acts)],
            "injected_joints": [int(j) + 1 for j in joints],
            "snr_target": float(snr),
            "snr": float(final / noise_acts),  # after the physical caps
            "params": {
                k: (np.asarray(v).tolist() if not isinstance(v, (float, int, str)) else v) for k, v in eff.items()
            },
        }
    logs = []
    for tr, t in zip(trajs, times):
        q, v, a, tau = true_torque(model, tr, t, effects)
        tau = tau + rng.uniform(-1, 1, tau.shape) * noise_amp
        logs.append(JointLog(t, q, v, tau, a if with_acceleration else None, {}, "simulated"))
    truth_all = {
        "effects": truth,
        "noise_level": float(level),
        "noise_amplitude_Nm": noise_amp.tolist(),
        "with_acceleration": bool(with_acceleration),
    }
    return logs[:n_fit], logs[n_fit:], truth_all


def _joint_mask(name, eff, n):
    """Joints a per-joint effect in its physical form acts on."""
    if name == "torque_scale":
        return np.asarray(eff["scale"]) != 1.0
    key = {"load_friction": "mu", "joint_elasticity": "compliance"}.get(name, "delta")
    return np.asarray(eff[key]) != 0.0


NEAR_FLOOR_SNR = (1.0, 1.3)  # "close to the noise floor": effect RMS about the noise RMS


def case_plan(n_cases, rng, effects=EFFECTS):
    """Injected effect sets: every 5th case null, then alternating single and double effects;
    every other double puts two per-joint effects on the same joints; every 3rd non-null case
    is drawn close to the noise floor (NEAR_FLOOR_SNR); accelerations logged in every other
    case of each kind."""
    plan, count = [], {0: 0, 1: 0, 2: 0}
    per_joint = [e for e in effects if e in PER_JOINT]
    non_null = 0
    for i in range(n_cases):
        same = False
        if i % 5 == 0:
            inj = []
        elif i % 2 == 1:
            inj = [effects[(i // 2) % len(effects)]]
        else:
            same = count[2] % 2 == 1 and len(per_joint) >= 2
            inj = [str(e) for e in rng.choice(per_joint if same else effects, size=2, replace=False)]
        near = bool(inj) and non_null % 3 == 2
        non_null += bool(inj)
        with_a = count[len(inj)] % 2 == 0  # alternate per kind: both forms for null/single/double
        count[len(inj)] += 1
        plan.append({"injected": inj, "with_acceleration": with_a, "same_joints": same, "near_floor": near})
    return plan


def _run_case(job):
    """One blind case (a process-pool job): make the logs, diagnose on the fit logs, score the
    check log once, compare names and values with the withheld truth."""
    from .gap import diagnose, single_threaded_blas

    model, seed, i, spec = job
    crng = np.random.default_rng([seed, i])
    with single_threaded_blas():
        fit, check, truth = make_case(
            model,
            crng,
            spec["injected"],
            spec["with_acceleration"],
            snr_range=NEAR_FLOOR_SNR if spec["near_floor"] else SNR_RANGE,
            same_joints=spec["same_joints"],
        )
        d = diagnose(model, fit, check)
    named = d.result["cause"]
    inj = spec["injected"]
    fitted = {e["name"]: e["params"] for e in d.result["effects"] if e["significant"]}
    case = {
        "case": i,
        **spec,
        "named": named,
        "form": d.form,
        "missed": [e for e in inj if e not in named],
        "false": [e for e in named if e not in inj],
        "truth": truth,
        "fitted": fitted,
        "rms_check": d.result["gap"]["rms_check"],
        "rms_check_after": d.result["combined"]["rms_check_after"],
        "cross_validation_reduction": d.result["cross_validation"]["reduction"],
        "joints_named": {e["name"]: e["joints"] for e in d.result["effects"] if e["significant"]},
        "value_errors": [err for e in inj if e in fitted for err in value_errors(e, truth["effects"][e], fitted[e])],
    }
    if "time_delay" in inj and "time_delay" in named:  # the right time law?
        case["time_law"] = {
            "injected": truth["effects"]["time_delay"]["params"].get("law", "shift"),
            "named": fitted["time_delay"]["time_law"],
        }
    return case


def _map(fn, jobs, workers):
    """fn over jobs, in `workers` processes when > 1 (results in job order)."""
    if workers <= 1:
        yield from map(fn, jobs)
        return
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(workers) as pool:
        yield from pool.map(fn, jobs)


def run_self_check(model, n_cases, seed, progress=None, workers=1):
    """Blind diagnosis of simulated cases (selection on the fit logs only, the check log scored
    once); returns (cases, summary, confusion)."""
    plan = case_plan(n_cases, np.random.default_rng(seed))
    cases = []
    for case in _map(_run_case, [(model, seed, i, spec) for i, spec in enumerate(plan)], workers):
        cases.append(case)
        if progress:
            progress(case)
    return cases, summarize(cases), confusion(cases)


# ---- parameter values against the withheld truth --------------------------------------------
def value_errors(name, truth, fitted):
    """Errors of a named effect's fitted parameters against the withheld truth: a list of
    {effect, quantity, unit, truth, fitted, abs_error, rel_error} (per-joint effects: on each
    injected joint the effect acts on, i.e. changes the torque by >= 20 % of its largest
    change; an elasticity on an axis whose torque does not depend on its angle is invisible
    and has no value to recover). rel_error is relative to the injected size."""
    tp = truth["params"]
    joints = [j - 1 for j in truth["injected_joints"] if j in truth.get("joints", truth["injected_joints"])]

    def rec(quantity, unit, t, f, size=None):
        size = abs(t) if size is None else size
        err = abs(f - t)
        return {
            "effect": name,
            "quantity": quantity,
            "unit": unit,
            "truth": float(t),
            "fitted": float(f),
            "abs_error": float(err),
            "rel_error": float(err / size) if size > 0 else None,
        }

    per_joint = {
        "coulomb_friction": ("delta", "delta_Fc_Nm", "ΔFc", "N·m"),
        "viscous_friction": ("delta", "delta_Fv_Nms_rad", "ΔFv", "N·m·s/rad"),
        "stribeck_friction": ("delta", "Fs_Nm", "Fs", "N·m"),
        "armature": ("delta", "delta_Ia_kgm2", "ΔIa", "kg·m²"),
        "torque_offset": ("delta", "offset_Nm", "offset", "N·m"),
        "load_friction": ("mu", "mu", "μ", "-"),
    }
    if name in per_joint:
        tk, fk, q, unit = per_joint[name]
        return [rec(q, unit, tp[tk][j], fitted[fk][j]) for j in joints]
    if name == "torque_scale":
        return [rec("scale", "-", tp["scale"][j], fitted["scale"][j], abs(tp["scale"][j] - 1.0)) for j in joints]
    if name == "joint_elasticity":
        return [
            r
            for j in joints
            for r in (
                rec(
                    "stiffness",
                    "N·m/rad",
                    1.0 / tp["compliance"][j],
                    1.0 / max(fitted["compliance_rad_per_Nm"][j], 1e-12),
                ),
                rec("compliance", "rad/(N·m)", tp["compliance"][j], fitted["compliance_rad_per_Nm"][j]),
            )
        ]
    if name == "time_delay":
        return [rec("d", "s", tp["delay_s"], fitted["delay_s"])]
    if name == "payload":
        m = tp["mass_kg"]
        com = np.asarray(tp["theta"][1:4]) / m
        err = float(np.linalg.norm(np.asarray(fitted["com_m"]) - com))
        return [
            rec("mass", "kg", m, fitted["mass_kg"]),
            {
                "effect": name,
                "quantity": "CoM",
                "unit": "m",
                "truth": float(np.linalg.norm(com)),
                "fitted": float(np.linalg.norm(fitted["com_m"])),
                "abs_error": err,
                "rel_error": err / float(np.linalg.norm(com)),
            },
        ]
    if name == "base_tilt":
        roll, pitch = tp["roll_pitch_rad"]
        size = max(abs(roll), abs(pitch))
        return [
            rec("roll", "rad", roll, fitted["roll_rad"], size),
            rec("pitch", "rad", pitch, fitted["pitch_rad"], size),
        ]
    return []


def error_table(cases):
    """Per effect and quantity: count, median and 90th percentile of the absolute and the
    relative error of the named injected effects."""
    rows = {}
    for c in cases:
        for e in c.get("value_errors", []):
            rows.setdefault((e["effect"], e["quantity"], e["unit"]), []).append(e)
    out = []
    for (effect, quantity, unit), recs in rows.items():
        ab = np.array([r["abs_error"] for r in recs])
        rel = np.array([r["rel_error"] for r in recs if r["rel_error"] is not None])
        out.append(
            {
                "effect": effect,
                "quantity": quantity,
                "unit": unit,
                "n": len(recs),
                "abs_median": float(np.median(ab)),
                "abs_p90": float(np.quantile(ab, 0.9)),
                "rel_median": float(np.median(rel)) if len(rel) else None,
                "rel_p90": float(np.quantile(rel, 0.9)) if len(rel) else None,
            }
        )
    order = {e: k for k, e in enumerate(EFFECTS)}
    return sorted(out, key=lambda r: (order[r["effect"]], r["quantity"]))


def error_markdown(table):
    lines = [
        "| effect | quantity | named cases·joints | median abs error | 90th pct abs error | median rel error "
        "| 90th pct rel error |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in table:
        rel = lambda x: "-" if x is None else f"{100 * x:.1f} %"  # noqa: E731
        lines.append(
            f"| {r['effect']} | {r['quantity']} [{r['unit']}] | {r['n']} | {r['abs_median']:.3g} "
            f"| {r['abs_p90']:.3g} | {rel(r['rel_median'])} | {rel(r['rel_p90'])} |"
        )
    return "\n".join(lines)


# ---- detection limits -----------------------------------------------------------------------
# Physical sizes tried per effect (time_delay once per law): the smallest found in >= 90 % of
# cases at a given noise level is the detection limit. Per-joint effects act on one random joint;
# the elasticity on one of the joints whose deflection gravity sees (ELASTIC_JOINTS): on the
# others the torque does not depend on the deflection and no size is visible.
DETECTION_LADDERS = {
    "coulomb_friction": ("ΔFc", "N·m", (0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)),
    "viscous_friction": ("ΔFv", "N·m·s/rad", (0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)),
    "stribeck_friction": ("Fs", "N·m", (0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)),
    "load_friction": ("μ", "-", (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2)),
    "armature": ("ΔIa", "kg·m²", (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)),
    "torque_offset": ("offset", "N·m", (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)),
    "torque_scale": ("scale deviation from 1", "-", (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1)),
    "payload": ("mass", "kg", (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)),
    "time_delay@shift": ("pure delay d", "s", (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05)),
    "time_delay@lag": ("lag d", "s", (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1)),
    "base_tilt": ("tilt", "rad", (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05)),
    "joint_elasticity": ("compliance 1/k", "rad/(N·m)", (1e-5, 2e-5, 5e-5, 1e-4, 2e-4, 5e-4, 1e-3, 3e-3)),
}
DETECTION_RATE = 0.9
ELASTIC_JOINTS = (1, 3, 5)  # 0-based: the Gen3's pitch joints 2, 4, 6


def effect_at(key, size, model, rng):
    """(effect name, effect in its physical form) of DETECTION_LADDERS key at `size`."""
    n = model.n
    name = key.split("@")[0]
    mask = np.zeros(n)
    mask[rng.choice(ELASTIC_JOINTS) if name == "joint_elasticity" and n == 7 else rng.integers(n)] = 1.0
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if name in ("coulomb_friction", "viscous_friction", "armature"):
        return name, {"delta": mask * size}
    if name == "stribeck_friction":
        return name, {"delta": mask * size, "vs": float(rng.choice(STRIBECK_VS))}
    if name == "torque_offset":
        return name, {"delta": mask * sign * size}
    if name == "load_friction":
        return name, {"mu": mask * size}
    if name == "torque_scale":
        return name, {"scale": 1.0 + mask * sign * size}
    if name == "joint_elasticity":
        return name, {"compliance": mask * size}
    if name == "payload":
        return name, {"mass_kg": size, "theta": payload_theta(model, size, rng)}
    if name == "time_delay":
        return name, ({"delay_s": size, "law": "lag"} if key.endswith("@lag") else {"delay_s": size})
    if name == "base_tilt":
        ang = rng.uniform(-1, 1, 2)
        return name, {"roll_pitch_rad": size * ang / np.abs(ang).max()}
    raise ValueError(key)


def _detection_case(job):
    """Is an effect of a given physical size named (and is anything else named)?"""
    from .gap import diagnose, single_threaded_blas

    model, seed, key, level, size, i = job
    rng = np.random.default_rng(
        [seed, list(DETECTION_LADDERS).index(key), int(round(1e4 * level)), int(round(1e9 * size)), i]
    )
    name, eff = effect_at(key, size, model, rng)
    with single_threaded_blas():
        fit, check, truth = make_case(model, rng, [name], i % 2 == 0, fixed={name: eff}, noise_level=level)
        named = diagnose(model, fit, check).result["cause"]
    return {"found": name in named, "false": [e for e in named if e != name], "snr": truth["effects"][name]["snr"]}


def _ladder(job):
    """Walk one effect's ladder at one noise level: start in the middle, go down while the rate
    holds, up while it does not; the smallest size found in >= DETECTION_RATE of the cases."""
    model, seed, key, level, n_cases = job
    sizes = DETECTION_LADDERS[key][2]
    tried = {}

    def rate(k):
        if k not in tried:
            res = [_detection_case((model, seed, key, level, sizes[k], i)) for i in range(n_cases)]
            tried[k] = {
                "size": sizes[k],
                "found": sum(r["found"] for r in res),
                "cases": n_cases,
                "false": sum(bool(r["false"]) for r in res),
                "snr_median": float(np.median([r["snr"] for r in res])),
            }
        return tried[k]["found"] / n_cases

    k = len(sizes) // 2
    if rate(k) >= DETECTION_RATE:
        while k > 0 and rate(k - 1) >= DETECTION_RATE:
            k -= 1
        limit = k
    else:
        while k + 1 < len(sizes) and rate(k + 1) < DETECTION_RATE:
            k += 1
        limit = k + 1 if k + 1 < len(sizes) else None
    quantity, unit, _ = DETECTION_LADDERS[key]
    return {
        "effect": key,
        "quantity": quantity,
        "unit": unit,
        "noise_level": level,
        "limit": sizes[limit] if limit is not None else None,
        "snr_at_limit": tried[limit]["snr_median"] if limit is not None else None,
        "tried": [tried[k] for k in sorted(tried)],
    }


def detection_limits(model, noise_levels=(0.01, 0.03), n_cases=10, seed=0, workers=1, keys=None, progress=None):
    """Per effect (time_delay per law) and noise level (fraction of each joint's torque range):
    the smallest size of DETECTION_LADDERS named in >= 90 % of n_cases blind cases (single
    effect, random joint, random trajectories; half without accelerations)."""
    jobs = [(model, seed, key, level, n_cases) for key in (keys or DETECTION_LADDERS) for level in noise_levels]
    out = []
    for r in _map(_ladder, jobs, workers):
        out.append(r)
        if progress:
            progress(r)
    return out


def detection_markdown(limits):
    levels = sorted({r["noise_level"] for r in limits})
    by = {(r["effect"], r["noise_level"]): r for r in limits}
    keys = list(dict.fromkeys(r["effect"] for r in limits))
    head = "| effect | quantity | " + " | ".join(f"found in ≥ 90 % at {100 * lv:g} % noise" for lv in levels) + " |"
    lines = [head, "|---|---|" + "---|" * len(levels)]
    for key in keys:
        r0 = by[(key, levels[0])]
        cells = []
        for lv in levels:
            r = by[(key, lv)]
            cells.append(
                "> largest tried" if r["limit"] is None else f"{r['limit']:g} {r['unit']} (SNR {r['snr_at_limit']:.2f})"
            )
        lines.append(f"| {key} | {r0['quantity']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summarize(cases):
    n_inj = sum(len(c["injected"]) for c in cases)
    n_found = sum(len(c["injected"]) - len(c["missed"]) for c in cases)
    n_named = sum(len(c["named"]) for c in cases)
    n_false = sum(len(c["false"]) for c in cases)
    nulls = [c for c in cases if not c["injected"]]
    return {
        "cases": len(cases),
        "injected_effects": n_inj,
        "injected_named": n_found,
        "injected_named_rate": n_found / n_inj if n_inj else 1.0,
        "named_effects": n_named,
        "false_effects": n_false,
        "false_effect_rate": n_false / n_named if n_named else 0.0,
        "cases_with_false_effect": sum(bool(c["false"]) for c in cases),
        "cases_with_false_effect_rate": sum(bool(c["false"]) for c in cases) / len(cases) if cases else 0.0,
        "null_cases": len(nulls),
        "null_correct": sum(not c["named"] for c in nulls),
        "exact_cases": sum(not c["missed"] and not c["false"] for c in cases),
        "time_law_named": sum("time_law" in c for c in cases),
        "time_law_correct": sum(c["time_law"]["injected"] == c["time_law"]["named"] for c in cases if "time_law" in c),
        "missed": [
            {"case": c["case"], "effect": e, "snr": c["truth"]["effects"][e]["snr"]} for c in cases for e in c["missed"]
        ],
        "near_floor": _named_rate([c for c in cases if c.get("near_floor")]),
        "same_joints": _named_rate([c for c in cases if c.get("same_joints")]),
        "parameter_errors": error_table(cases),
    }


def _named_rate(cases):
    inj = sum(len(c["injected"]) for c in cases)
    found = sum(len(c["injected"]) - len(c["missed"]) for c in cases)
    return {
        "cases": len(cases),
        "injected_effects": inj,
        "injected_named": found,
        "cases_with_false_effect": sum(bool(c["false"]) for c in cases),
    }


def confusion(cases, effects=EFFECTS):
    """counts[injected][named]. Per case and injected effect: its own column when named, else
    'none' (missed); every falsely named effect is counted in the row of each injected effect
    of that case (or the 'none' row for a null case). A null case naming nothing counts
    [none][none]. A second injected effect that is named is not a confusion, so it is not
    counted in the other effect's row."""
    labels = list(effects) + ["none"]
    table = {r: {c: 0 for c in labels} for r in labels}
    for c in cases:
        rows = c["injected"] or ["none"]
        for r in rows:
            if r != "none":
                table[r][r if r in c["named"] else "none"] += 1
            for f in c["false"]:
                table[r][f] += 1
            if r == "none" and not c["false"]:
                table["none"]["none"] += 1
    return table


def confusion_markdown(table):
    labels = list(table)
    short = {e: "".join(w[0] for w in e.split("_")) if e != "none" else "none" for e in labels}
    head = "| injected \\ named | " + " | ".join(short[c] for c in labels) + " |"
    sep = "|---" * (len(labels) + 1) + "|"
    rows = [
        f"| {r} | " + " | ".join(str(table[r][c]) if table[r][c] else "." for c in labels) + " |"
        for r in labels
        if any(table[r].values())
    ]
    key = "Columns: " + ", ".join(f"{short[e]} = {e}" for e in labels)
    return "\n".join([head, sep, *rows, "", key])


# ---- logs from the simulated real arm (systems/real_arm.py, Drake) ---------------------------
REAL_ARM_EFFECTS = {  # diagnosis vocabulary -> scenario.plant.effects field (real_arm's law)
    "torque_offset": "torque_sensor_offset_Nm",
    "torque_scale": "torque_sensor_scale",
    "time_delay": "time_delay_s",  # or torque_sensor_lag_s (a first-order lag of the sensor)
    "base_tilt": "base_tilt_rad",
    "joint_elasticity": "joint_stiffness_Nm_rad",
}


def real_arm_log(effects, seed, duration_s=10.0, rate_hz=RATE_HZ, noise_ratio=0.01, kp=400.0, kd=40.0):
    """One log of the Drake-simulated real arm (discrete MultibodyPlant, 1 kHz, its own friction,
    sensor and effect laws) tracking a random smooth trajectory with computed torque + PD on the
    nominal model. `effects`: {scenario.plant.effects field: value}. No acceleration column
    (the real arm has no acceleration sensor): the diagnosis uses the momentum form."""
    from safesysid.scenario import load_scenario

    from .arm_tracking import track_trajectory
    from .robot_model import load_robot

    overrides = {
        "payload": {"dumbbell": "none"},
        "seed": int(seed),
        "noise": {"torque_ratio": noise_ratio, "torque_floor_Nm": 0.05},
        "plant": {
            "time_step_s": 0.001,
            "effects": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in effects.items()},
        },
    }
    scenario = load_scenario(overrides=overrides)
    robot = load_robot(coulomb_smoothing=scenario.robot.coulomb_smoothing_rad_s)
    rng = np.random.default_rng(seed)
    traj = random_trajectory(robot, rng)
    log = track_trajectory(scenario, robot, robot, traj, seed, duration_s, rate_hz, kp, kd, skip_s=0.2)
    g0 = rng.uniform(0.3, 0.7) * duration_s
    return log.slice((log.t < g0) | (log.t > g0 + GAP_S)), robot


def run_real_arm_check(seed=0, progress=None, duration_s=6.0, only=None):
    """Blind diagnosis of real-arm logs: no effect, then each effect real_arm implements.
    Returns a list of {injected, named, ...}. Slow (Drake simulation, ~10 s per log)."""
    from .gap import diagnose, single_threaded_blas

    cases = [({}, [])]
    cases.append(({"torque_sensor_offset_Nm": [0.0, 1.5, 0.0, -1.0, 0.0, 0.0, 0.0]}, ["torque_offset"]))
    cases.append(({"torque_sensor_scale": [1.0, 1.0, 1.0, 1.08, 1.0, 1.0, 1.0]}, ["torque_scale"]))
    cases.append(({"time_delay_s": 0.01}, ["time_delay"]))
    cases.append(({"base_tilt_rad": [0.03, 0.0]}, ["base_tilt"]))
    cases.append(({"joint_stiffness_Nm_rad": [1e6, 300.0, 1e6, 300.0, 1e6, 1e6, 1e6]}, ["joint_elasticity"]))
    cases.append(({"torque_sensor_lag_s": 0.05}, ["time_delay"]))  # filtered torque signal (real Gen3 logs)
    out = []
    with single_threaded_blas():
        for k, (eff, inj) in enumerate(cases):
            if only is not None and k not in only:
                continue
            logs = []
            for j in range(3):
                log, robot = real_arm_log(eff, seed=1000 * seed + 10 * k + j, duration_s=duration_s)
                logs.append(log)
            d = diagnose(robot, logs[:2], logs[2:])
            named = d.result["cause"]
            out.append(
                {
                    "injected": inj,
                    "named": named,
                    "effects": eff,
                    "rms_check": d.result["gap"]["rms_check"],
                    "rms_check_after": d.result["combined"]["rms_check_after"],
                    "plant_effects": d.corrected["plant_effects"],
                }
            )
            if progress:
                progress(out[-1])
    return out
