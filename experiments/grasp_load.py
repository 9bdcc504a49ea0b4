"""Peak load on the grasp of the held dumbbell over runs: `python experiments/grasp_load.py
RUN_DIR ...` (folders of `safesysid run`, their log.csv and summary.json).

The authors' public experiment README says the stock Gen3 gripper cannot hold dumbbells over 7 lb
stably; a grasp that slips fails whatever the controller. This prints, per run, what the grasp must
transmit: the peak of m |a_c - g| (force on the dumbbell centre, the grasp point), the peak angular
acceleration of the end effector and the 99th percentile of |da_c/dt| (jerk, the high-frequency
content a chattering robust input adds), from the logged q, v at the plant's rate: the grasp point's
spatial velocity by Drake's Jacobian, differentiated in time.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from pydrake.multibody.tree import JacobianWrtVariable
from safesysid.joint_log import read_joint_log
from safesysid.systems.model.robot_model import load_robot, make_plant

GRAVITY = np.array([0.0, 0.0, -9.81])


def grasp_load(run_dir: str | Path) -> dict:
    """{method, dumbbell mass, peak force N, peak angular acceleration rad/s^2, jerk p99 m/s^3} of one run."""
    run_dir = Path(run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    robot = load_robot()
    plant, _, _ = make_plant(robot.source)
    if not plant.is_finalized():
        plant.Finalize()
    ctx = plant.CreateDefaultContext()
    ee = plant.GetBodyByName(robot.body_names[robot.end_effector]).body_frame()
    log = read_joint_log(run_dir / "log.csv", robot.n)
    spatial_velocity = np.empty((len(log.t), 6))
    for k, (qk, vk) in enumerate(zip(log.q, log.v)):
        plant.SetPositions(ctx, qk)
        plant.SetVelocities(ctx, vk)
        J = plant.CalcJacobianSpatialVelocity(
            ctx, JacobianWrtVariable.kV, ee, robot.extra["grasp_point"], plant.world_frame(), plant.world_frame()
        )
        spatial_velocity[k] = J @ vk
    accel = np.gradient(spatial_velocity, log.t, axis=0)
    mass = float(summary["payload_true"]["theta"][0]) if "payload_true" in summary else np.nan
    dumbbell_mass = mass - robot.theta[robot.ee_slice][0]  # the true end effector minus the bare one
    linear = accel[:, 3:] - GRAVITY
    return {
        "method": summary["method"],
        "dumbbell_kg": round(dumbbell_mass, 3),
        "peak_force_N": float(dumbbell_mass * np.linalg.norm(linear, axis=1).max()),
        "peak_angular_acceleration": float(np.linalg.norm(accel[:, :3], axis=1).max()),
        "jerk_p99": float(np.percentile(np.linalg.norm(np.gradient(accel[:, 3:], log.t, axis=0), axis=1), 99)),
    }


if __name__ == "__main__":
    for path in sys.argv[1:]:
        print(path, json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in grasp_load(path).items()}))
