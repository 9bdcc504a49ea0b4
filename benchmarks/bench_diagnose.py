"""Gap diagnosis under the honest protocol (selection on the fit logs only, inner
cross-validation; check logs scored once): time for 3 logs of 1 500 samples including the
inner cross-validation (target <= 10 s), the real Kinova Gen3 nested leave-one-run-out
(held-out RMS before/after per joint, all and unsaturated samples; targets >= 85 % / >= 88 %),
and the withheld-effect self-check (full run only: 40 blind cases x seeds 1, 2, 11, with
parameter errors). `python benchmarks/bench_diagnose.py --detection-limits` adds the
detection-limit table (slow: about 700 blind diagnoses)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from safesysid.joint_log import JointLog, read_joint_log
from safesysid.systems import diagnosis as dg
from safesysid.systems.robot_model import load_robot

SHARED = Path(__file__).resolve().parents[2] / "shared"
REAL = SHARED / "data" / "kinova_gen3_real"
REFERENCE_URDF = SHARED / "models" / "reference" / "kinova_gen3_raptor_nomesh.urdf"
SELF_CHECK_SEEDS = (1, 2, 11)


def logs_3x1500(model, seed, with_a):
    """Three simulated Kinova logs of 1 500 samples (one 0.5 s gap each) with a 20 ms delay and
    viscous friction on joint 1 withheld."""
    rng = np.random.default_rng(seed)
    logs = []
    for _ in range(3):
        traj = dg.random_trajectory(model, rng)
        t = np.arange(1500) / dg.RATE_HZ
        t[750:] += dg.GAP_S
        effects = {"time_delay": {"delay_s": 0.02}, "viscous_friction": {"delta": np.r_[2.0, np.zeros(model.n - 1)]}}
        q, v, a, tau = dg.true_torque(model, traj, t, effects)
        tau = tau + 0.5 * rng.uniform(-1, 1, tau.shape)
        logs.append(JointLog(t, q, v, tau, a if with_a else None))
    return logs


def timing_3x1500(seed=0):
    """Wall and CPU time of one diagnosis (2 fit logs with their inner folds, 1 check log)."""
    model = load_robot()
    out = {}
    for with_a in (True, False):
        logs = logs_3x1500(model, seed, with_a)
        t0, c0 = time.perf_counter(), time.process_time()
        d = dg.diagnose(model, logs[:2], logs[2:])
        out["inverse_dynamics" if with_a else "momentum"] = {
            "wall_time_s": time.perf_counter() - t0,
            "cpu_time_s": time.process_time() - c0,
            "cause": d.result["cause"],
            "test_reduction": d.result["test"]["reduction"],
            "cross_validation_reduction": d.result["cross_validation"]["reduction"],
        }
    return out


def real_leave_one_out():
    if not (REAL / "run1.csv").is_file() or not REFERENCE_URDF.is_file():
        return {"skipped": f"{REAL} or {REFERENCE_URDF} not available"}
    model = load_robot(REFERENCE_URDF)
    logs = [read_joint_log(REAL / f"run{k}.csv", model.n) for k in (1, 2, 3)]
    folds, out = dg.leave_one_out(model, logs)
    for f, d in zip(out["folds"], folds):
        f["worst_regimes"] = sorted(d.result["gap"]["where"]["regimes"].items(), key=lambda x: -x[1])[:2]
    out.update(target_reduction=0.85, target_reduction_unsaturated=0.88, reference_cva_rms_after=1.9)
    return out


def self_check(seeds=SELF_CHECK_SEEDS, cases=40, workers=2):
    """The blind self-check per seed and pooled over the seeds (confusion, value errors)."""
    model = load_robot()
    out, pooled = {}, []
    for seed in seeds:
        t0 = time.perf_counter()
        seed_cases, summary, _ = dg.run_self_check(model, cases, seed, workers=workers)
        summary["wall_time_s"] = time.perf_counter() - t0
        out[f"seed_{seed}"] = summary
        pooled += seed_cases
    out["pooled"] = dg.summarize(pooled)
    out["pooled_confusion_markdown"] = dg.confusion_markdown(dg.confusion(pooled))
    out["pooled_errors_markdown"] = dg.error_markdown(out["pooled"]["parameter_errors"])
    return out


def run(quick: bool = False) -> dict:
    out = {"timing_3x1500": timing_3x1500(), "target_time_s": 10.0}
    out["real_leave_one_run_out"] = real_leave_one_out()
    if not quick:
        out["self_check_40"] = self_check()
    return out


if __name__ == "__main__":
    import json

    if "--detection-limits" in sys.argv:  # optionally followed by KEY,KEY (DETECTION_LADDERS keys)
        rest = sys.argv[sys.argv.index("--detection-limits") + 1 :]
        keys = rest[0].split(",") if rest and not rest[0].startswith("--") else None
        t0 = time.perf_counter()
        limits = dg.detection_limits(
            load_robot(),
            workers=2,
            seed=0,
            keys=keys,
            progress=lambda r: print(json.dumps(r, default=float), file=sys.stderr, flush=True),
        )
        print(dg.detection_markdown(limits))
        print(
            json.dumps({"detection_limits": limits, "wall_time_s": time.perf_counter() - t0}, indent=2, default=float)
        )
    else:
        print(json.dumps(run(quick="--quick" in sys.argv), indent=2, default=float))
