"""What a corrected model (`corrected_model.yaml`, written by `safesysid diagnose`) changes, for
its consumers: the scenario (`robot.corrected_model`), the simulated arm built from it, and
`safesysid sysid --model`. It changes a loaded RobotModel (the starting model, which
systems/config.py starting_robot loads) and loads nothing itself.

One file, two sides of one model truth:
  robot side   Coulomb and viscous friction, armature and torque offset: terms of the
               RobotModel that plant, controller, planner and estimator share (the offset is
               the model's beta, counted once: not again as a sensor offset);
  plant side   everything the RobotModel has no term for, as scenario `plant.effects` fields:
               a first-order lag of the torque signal (torque_sensor_lag_s), a pure delay
               (time_delay_s when the torque leads the motion: actuation; torque_sensor_delay_s
               when it lags: the reading arrives late), base tilt, joint elasticity, torque
               scale, load-dependent and Stribeck friction.
A diagnosed payload has no counterpart in the simulated arm (its payload is the scenario's
dumbbell): asking for it is an error naming the effect. Every
parameter applies to all joints (per-joint lists of n values); `joints` only says where the
effect was found to matter, as in diagnosis.json.

The params of each effect are diagnosis.effect_params' (units in the key names); the time law is
`time_law: lag | shift` (from the `law` text in older files). The file is read by
systems/model/corrected_model.py's reader (CorrectedModel, CorrectedEffect).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from safesysid.systems.model.robot_model import RobotModel

if TYPE_CHECKING:
    from safesysid.systems.model.corrected_model import CorrectedEffect, CorrectedModel

# effect -> (JointParameters field, params key of the increment on the starting model)
ROBOT_SIDE = {
    "coulomb_friction": ("coulomb", "delta_Fc_Nm"),
    "viscous_friction": ("viscous", "delta_Fv_Nms_rad"),
    "armature": ("armature", "delta_Ia_kgm2"),
    "torque_offset": ("offset", "offset_Nm"),
}
RIGID = 1e12  # N m/rad: the stiffness of a joint without diagnosed compliance (rigid)


class CorrectionError(ValueError):
    """A corrected model that cannot be applied; the message names the file and the field."""


def find_effect(corr: CorrectedModel, name: str) -> CorrectedEffect | None:
    return next((e for e in corr.effects if e.name == name), None)


def read_correction(path: str | Path) -> CorrectedModel:
    """A corrected_model.yaml through the diagnosis' own reader (one schema, one reader); its
    error (naming file and field) as a CorrectionError."""
    from safesysid.systems.model.corrected_model import CorrectedModelError, read_corrected_model  # no cycle via config

    try:
        return read_corrected_model(path)
    except CorrectedModelError as err:
        raise CorrectionError(str(err)) from err


def _param(corr, effect, key, n=None):
    """A parameter of an effect (a per-joint array when n is given); CorrectionError names it."""
    k = corr.effects.index(effect)
    where = f"{corr.path}: effects[{k}].params.{key}"
    if key not in effect.params:
        raise CorrectionError(f"{where}: missing")
    try:
        value = np.asarray(effect.params[key], float)
    except (TypeError, ValueError):
        raise CorrectionError(f"{where}: expected numbers") from None
    if n is not None and value.shape != (n,):
        raise CorrectionError(f"{where}: {value.size} values for a model with {n} joints")
    if not np.all(np.isfinite(value)):
        raise CorrectionError(f"{where}: not finite")
    return value


def time_law(effect: CorrectedEffect) -> str:
    """'lag' (first-order lag of the torque signal) or 'shift' (pure delay) of a time_delay."""
    return effect.params["time_law"]  # the reader fills it in from the prose law of older files


def torque_lag_s(corr: CorrectedModel) -> float | list[float]:
    """Time constant of a diagnosed first-order lag of the torque signal (0 when none), for the
    estimator: [lo, hi] when the effect carries `intervals.delay_s` (the diagnosed lag is an
    estimate; the estimator encloses over the interval, widened to hold the point value too),
    else the point value."""
    e = find_effect(corr, "time_delay")
    if e is None or time_law(e) != "lag":
        return 0.0
    d = float(_param(corr, e, "delay_s"))
    pair = (getattr(e, "intervals", None) or {}).get("delay_s")
    if pair is None or any(x is None for x in pair):  # null: the diagnosis has no interval
        return d
    lo, hi = (float(x) for x in pair)
    if not 0 <= lo <= hi:
        raise CorrectionError(f"{corr.path}: effects[{corr.effects.index(e)}].intervals.delay_s: needs 0 <= lo <= hi")
    return [min(lo, d), max(hi, d)]


def torque_shift_s(corr: CorrectedModel) -> float:
    """A diagnosed pure delay of the torque against the motion, signed as the diagnosis gives it
    (> 0: the torque lags, a late reading; < 0: it leads, a late torque; 0 when none), which is
    estimator.torque_delay_s."""
    e = find_effect(corr, "time_delay")
    return float(_param(corr, e, "delay_s")) if e is not None and time_law(e) == "shift" else 0.0


def corrected_robot(robot: RobotModel, corr: CorrectedModel) -> RobotModel:
    """The RobotModel with the robot-side corrections (increments on `robot`, the starting
    model): joint parameters and the friction part of theta (Fc, Fv, Ia, beta per joint)."""
    jp = robot.joint_params
    changes = {}
    for name, (attr, key) in ROBOT_SIDE.items():
        e = find_effect(corr, name)
        if e is not None:
            changes[attr] = getattr(jp, attr) + _param(corr, e, key, robot.n)
    if not changes:
        return robot
    jp = dataclasses.replace(jp, **changes)
    theta = robot.theta.copy()
    theta[10 * robot.n :] = jp.friction_theta()
    return dataclasses.replace(robot, joint_params=jp, theta=theta)


def plant_effects(corr: CorrectedModel, n: int | None = None) -> dict:
    """{scenario plant.effects field: value} of the plant-side effects (see module docstring)."""
    out = {}
    for e in corr.effects:
        name, k = e.name, corr.effects.index(e)
        if name == "time_delay":
            d = float(_param(corr, e, "delay_s"))
            if time_law(e) == "lag":
                out["torque_sensor_lag_s"] = d
            elif d <= 0:
                out["time_delay_s"] = -d  # torque leads the motion: an actuation delay
            else:
                out["torque_sensor_delay_s"] = d  # torque lags the motion: the reading arrives late
        elif name == "torque_scale":
            out["torque_sensor_scale"] = _param(corr, e, "scale", n).tolist()
        elif name == "base_tilt":
            out["base_tilt_rad"] = [float(_param(corr, e, "roll_rad")), float(_param(corr, e, "pitch_rad"))]
        elif name == "joint_elasticity":
            c = _param(corr, e, "compliance_rad_per_Nm", n)
            out["joint_stiffness_Nm_rad"] = [1.0 / x if x > 1.0 / RIGID else RIGID for x in c]
        elif name == "load_friction":
            out["load_friction_mu"] = _param(corr, e, "mu", n).tolist()
        elif name == "stribeck_friction":
            out["stribeck_friction_Nm"] = _param(corr, e, "Fs_Nm", n).tolist()
            out["stribeck_velocity_rad_s"] = float(_param(corr, e, "vs_rad_s"))
        elif name == "payload":
            raise CorrectionError(
                f"{corr.path}: effects[{k}] payload: a diagnosed payload has no counterpart in "
                "the simulated arm (the scenario's payload is payload.dumbbell)"
            )
        elif name not in ROBOT_SIDE:
            raise CorrectionError(f"{corr.path}: effects[{k}].name: unknown effect {name!r}")
    return out
