"""Gap diagnosis: time for 3 logs of 1 500 samples (target <= 20 s), the real Kinova Gen3
leave-one-run-out (held-out RMS before/after per joint, target reduction >= 85 %), and the
withheld-effect self-check (full run only: >= 40 blind cases)."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from safesysid.joint_log import JointLog, read_joint_log
from safesysid.systems import gap
from safesysid.systems import gap_simulate as gs
from safesysid.systems.robot_model import load_robot

SHARED = Path(__file__).resolve().parents[2] / "shared"
REAL = SHARED / "data" / "kinova_gen3_real"
REFERENCE_URDF = SHARED / "models" / "reference" / "kinova_gen3_raptor_nomesh.urdf"


def timing_3x1500(seed=0):
    """Three simulated Kinova logs of 1 500 samples (2 fit, 1 check), a delay and viscous
    friction withheld; both residual forms."""
    model = load_robot()
    rng = np.random.default_rng(seed)
    out = {}
    for with_a in (True, False):
        logs = []
        for _ in range(3):
            traj = gs.random_trajectory(model, rng)
            t = np.arange(1500) / gs.RATE_HZ
            t[750:] += gs.GAP_S  # one 0.5 s gap, 1 500 samples kept
            effects = {"time_delay": {"delay_s": 0.02}, "viscous_friction": {"delta": np.r_[2.0, np.zeros(model.n - 1)]}}
            q, v, a, tau = gs.true_torque(model, traj, t, effects)
            tau = tau + 0.5 * rng.uniform(-1, 1, tau.shape)
            logs.append(JointLog(t, q, v, tau, a if with_a else None))
        t0 = time.perf_counter()
        d = gap.diagnose(model, logs[:2], logs[2:])
        out["inverse_dynamics" if with_a else "momentum"] = {
            "wall_time_s": time.perf_counter() - t0, "cause": d.result["cause"],
            "reduction": d.result["combined"]["reduction"]}
    return out


def real_leave_one_out():
    if not (REAL / "run1.csv").is_file() or not REFERENCE_URDF.is_file():
        return {"skipped": f"{REAL} or {REFERENCE_URDF} not available"}
    model = load_robot(REFERENCE_URDF)
    logs = [read_joint_log(REAL / f"run{k}.csv", model.n) for k in (1, 2, 3)]
    folds, out = gap.leave_one_out(model, logs)
    for f, d in zip(out["folds"], folds):
        f["worst_regimes"] = sorted(d.result["gap"]["where"]["regimes"].items(), key=lambda x: -x[1])[:2]
    out.update(target_reduction=0.85, reference_cva_rms_after=1.9)
    return out


def run(quick: bool = False) -> dict:
    out = {"timing_3x1500": timing_3x1500()}
    out["target_time_s"] = 20.0
    out["real_leave_one_run_out"] = real_leave_one_out()
    if not quick:
        t0 = time.perf_counter()
        _, summary, _ = gs.run_self_check(load_robot(), 40, seed=1)
        summary["wall_time_s"] = time.perf_counter() - t0
        out["self_check_40"] = summary
    return out


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick="--quick" in sys.argv), indent=2, default=float))
