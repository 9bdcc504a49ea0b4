"""The effects a diagnosis can name: their column groups, parameter bounds and physical
parameters (JSON), and the corrected joint parameters of a selection.

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
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from safesysid.systems.model.corrected_model import EFFECT_NAMES as EFFECTS
from safesysid.systems.model.robot_model import RobotModel

WHOLE_ARM = ("payload", "time_delay", "base_tilt")  # one set of parameters for the arm
PER_JOINT = tuple(e for e in EFFECTS if e not in WHOLE_ARM)  # one parameter (or more) per joint
STRIBECK_VELOCITIES = tuple(round(0.02 * 1.5**k, 4) for k in range(7))  # rad/s grid for vs (0.02..0.23)
Params = dict[str, np.ndarray]  # fitted parameters by column group (effect_groups)
TIME_LAWS = {"time_delay@shift": "shift", "time_delay@lag": "lag"}  # model-side time laws (grid-searched d)


MAX_DELAY_S = 0.2


MAX_TILT = 0.2
MAX_COMPLIANCE = 0.02  # rad/(N m)
MAX_LOAD_FRICTION = 0.5  # friction torque per unit transmitted torque


def effect_groups(effect: str) -> list[str]:
    """Column groups that realise an effect (Stribeck: one per grid velocity, alternatives)."""
    if effect == "stribeck_friction":
        return [f"stribeck_friction@{vs}" for vs in STRIBECK_VELOCITIES]
    if effect == "time_delay":  # a pure delay or a first-order lag (see TIME_LAWS)
        return list(TIME_LAWS)
    return [effect]


def group_bounds(model: RobotModel, group: str, k: int) -> tuple[np.ndarray, np.ndarray]:
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


def effect_params(model: RobotModel, effect: str, params: Params, *, group_used: str) -> dict:
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


def group_of(effect: str, params: Params) -> str:
    return next(g for g in params if g.split("@")[0] == effect)


def corrected_parameters(model: RobotModel, selected: Sequence[str], params: Params) -> dict:
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
        g = group_of(e, params)
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
            other[e] = effect_params(model, e, params, group_used=g)
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
