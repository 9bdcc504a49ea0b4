"""Withheld-effect logs for the diagnosis self-check (`safesysid diagnose --self-check`):
simulated logs of a RobotModel with effects withheld from it.

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
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from safesysid.systems.model import inertial
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.robot_model import RobotModel

from .design import segments
from .effects import PER_JOINT
from .time_laws import first_order_lag

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


def random_trajectory(model: RobotModel, rng: np.random.Generator) -> Trajectory:
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


def sample_times(rng: np.random.Generator, duration_s: float) -> np.ndarray:
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


def payload_theta(model: RobotModel, mass: float, rng: np.random.Generator) -> np.ndarray:
    """A solid cylinder held near the grasp point (end-effector frame), physically consistent."""
    c = model.extra.get("grasp_point", np.zeros(3)) + rng.uniform(-0.05, 0.05, 3)
    r, h = 0.04, 0.15
    i_c = mass * np.diag([(3 * r * r + h * h) / 12, (3 * r * r + h * h) / 12, r * r / 2])
    return inertial.from_mass_com_inertia(mass, c, i_c)


def true_torque(
    model: RobotModel, traj: Trajectory, t: np.ndarray, *, effects: dict[str, dict]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
            model.inverse_dynamics(*true_torque(model, tr, t, effects={name: eff})[:3]) - c[3]
            for tr, t, c in zip(trajs, times, clean)
        ]
    else:
        contrib = [true_torque(model, tr, t, effects={name: eff})[3] - c[3] for tr, t, c in zip(trajs, times, clean)]
    return np.sqrt(np.mean(np.concatenate(contrib) ** 2, 0))


def make_case(
    model: RobotModel,
    rng: np.random.Generator,
    injected: Sequence[str],
    with_acceleration: bool,
    *,
    n_fit: int = 2,
    n_check: int = 1,
    duration_s: float = 10.0,
    snr_range: tuple[float, float] = SNR_RANGE,
    same_joints: bool = False,
    fixed: dict[str, dict] | None = None,
    noise_level: float | None = None,
) -> tuple[list[JointLog], list[JointLog], dict]:
    """Fit and check logs with the `injected` effects withheld from `model`.

    Effect sizes are drawn as an SNR in `snr_range` (module docstring) unless `fixed` gives an
    effect in its physical form ({name: effect}, e.g. from effect_at: detection limits).
    same_joints: every per-joint effect acts on the joints of the first one (two effects on the
    same joint). noise_level: fraction of each joint's torque range (default: drawn).
    Returns (fit_logs, check_logs, truth) where truth records every effect's parameters, the
    achieved SNR, the joints it acts on and the joints it was injected on (1-based)."""
    trajs = [random_trajectory(model, rng) for _ in range(n_fit + n_check)]
    times = [sample_times(rng, duration_s) for _ in trajs]
    clean = [true_torque(model, tr, t, effects={}) for tr, t in zip(trajs, times)]
    tau_all = np.concatenate([c[3] for c in clean])
    level = rng.uniform(*NOISE_LEVEL_RANGE) if noise_level is None else float(noise_level)
    noise_amp = level * (tau_all.max(0) - tau_all.min(0))
    noise_rms = noise_amp / np.sqrt(3.0)
    effects, truth = {}, {}
    shared = None  # joints of the first per-joint effect (same_joints)
    for name in injected:
        snr = rng.uniform(*snr_range)
        eff, acts, joints, final, noise_acts = _draw_effect(
            model,
            name,
            rng,
            snr=snr,
            sim=(trajs, times, clean, noise_rms),
            joints=shared if same_joints else None,
            fixed=fixed,
        )
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
        q, v, a, tau = true_torque(model, tr, t, effects=effects)
        tau = tau + rng.uniform(-1, 1, tau.shape) * noise_amp
        logs.append(JointLog(t, q, v, tau, a if with_acceleration else None, {}, "simulated"))
    truth_all = {
        "effects": truth,
        "noise_level": float(level),
        "noise_amplitude_Nm": noise_amp.tolist(),
        "with_acceleration": bool(with_acceleration),
    }
    return logs[:n_fit], logs[n_fit:], truth_all


def _draw_effect(model, name, rng, *, snr, sim, joints, fixed):
    """(effect, mask of the joints it acts on, joints it was injected on, achieved rms, noise rms
    on those joints) of one injected effect scaled to `snr` (under its physical cap); `joints`
    given: inject on them (same_joints); sim = (trajectories, times, clean torques, noise rms)."""
    n = model.n
    trajs, times, clean, noise_rms = sim
    shared = joints
    for _attempt in range(MAX_DRAWS):
        # Joints and shape are redrawn when the physical cap keeps the effect far below the
        # drawn SNR (e.g. a stiff joint on an axis whose torque hardly depends on its angle).
        if name not in PER_JOINT:
            joints = np.arange(n)
        elif shared is not None:
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
        final = np.sqrt(np.mean(_effect_rms(model, name, eff, trajs, times, clean)[acts] ** 2)) if acts.any() else 0.0
        if final >= MIN_SNR_AFTER_CAP * noise_acts:
            break
    return eff, acts, joints, final, noise_acts


def _joint_mask(name, eff, n):
    """Joints a per-joint effect in its physical form acts on."""
    if name == "torque_scale":
        return np.asarray(eff["scale"]) != 1.0
    key = {"load_friction": "mu", "joint_elasticity": "compliance"}.get(name, "delta")
    return np.asarray(eff[key]) != 0.0
