"""Blind diagnosis of logs of the Drake-simulated real arm (systems/plant/station.py): each effect
real_arm implements, in its own law, named back by the diagnosis.
"""

from __future__ import annotations

from collections.abc import Callable, Container

import numpy as np
from safesysid.systems.math.blas import single_threaded_blas
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.robot_model import RobotModel

from ..config import PlantEffects, Scenario
from .diagnose import diagnose
from .simulate import GAP_S, RATE_HZ, random_trajectory

# ---- logs from the simulated real arm (systems/plant/station.py, Drake) ---------------------------
REAL_ARM_EFFECTS = {  # diagnosis vocabulary -> scenario.plant.effects field (real_arm's law)
    "torque_offset": "torque_sensor_offset_Nm",
    "torque_scale": "torque_sensor_scale",
    "time_delay": "time_delay_s",  # or torque_sensor_lag_s (a first-order lag of the sensor)
    "base_tilt": "base_tilt_rad",
    "joint_elasticity": "joint_stiffness_Nm_rad",
}


def real_arm_log(
    effects: dict,
    seed: int,
    *,
    duration_s: float = 10.0,
    rate_hz: float = RATE_HZ,
    noise_ratio: float = 0.01,
    kp: float = 400.0,
    kd: float = 40.0,
) -> tuple[JointLog, RobotModel]:
    """One log of the Drake-simulated real arm (discrete MultibodyPlant, 1 kHz, its own friction,
    sensor and effect laws) tracking a random smooth trajectory with computed torque + PD on the
    nominal model. `effects`: {scenario.plant.effects field: value}. No acceleration column
    (the real arm has no acceleration sensor): the diagnosis uses the momentum form."""
    from safesysid.systems.model.robot_model import load_robot
    from safesysid.systems.plant.arm_tracking import track_trajectory

    # The default scenario (its schema's defaults) with these fields set.
    scenario = Scenario(seed=int(seed))
    scenario.source = "real_arm_log"
    scenario.payload.dumbbell = "none"
    scenario.noise.torque_ratio, scenario.noise.torque_floor_Nm = noise_ratio, 0.05
    scenario.plant.time_step_s = 0.001
    scenario.plant.effects = PlantEffects(
        **{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in effects.items()}
    )
    robot = load_robot(coulomb_smoothing=scenario.robot.coulomb_smoothing_rad_s)
    rng = np.random.default_rng(seed)
    traj = random_trajectory(robot, rng)
    log = track_trajectory(
        scenario, robot, robot, traj, seed, duration_s, rate_hz=rate_hz, kp_Nm_rad=kp, kd_Nms_rad=kd, skip_s=0.2
    )
    g0 = rng.uniform(0.3, 0.7) * duration_s
    return log.slice((log.t < g0) | (log.t > g0 + GAP_S)), robot


def run_real_arm_check(
    *,
    seed: int = 0,
    progress: Callable[[dict], None] | None = None,
    duration_s: float = 6.0,
    only: Container[int] | None = None,
) -> list[dict]:
    """Blind diagnosis of real-arm logs: no effect, then each effect real_arm implements.
    Returns a list of {injected, named, ...}. Slow (Drake simulation, ~10 s per log)."""

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
