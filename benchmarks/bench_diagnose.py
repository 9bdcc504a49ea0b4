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
from safesysid.benchmarks.scaling import load_average, plot, png, timed
from safesysid.joint_log import read_joint_log
from safesysid.systems import diagnosis as dg
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.robot_model import load_robot

SHARED = Path(__file__).resolve().parents[2] / "shared"
REAL = SHARED / "data" / "kinova_gen3_real"
REFERENCE_URDF = SHARED / "models" / "reference" / "kinova_gen3_raptor_nomesh.urdf"
SELF_CHECK_SEEDS = (1, 2, 11)


def logs_3x1500(model, seed, with_a, count=3, samples=1500):
    """`count` simulated Kinova logs of `samples` samples (one 0.5 s gap each, in the middle) with
    a 20 ms delay and viscous friction on joint 1 withheld."""
    rng = np.random.default_rng(seed)
    logs = []
    for _ in range(count):
        traj = dg.random_trajectory(model, rng)
        t = np.arange(samples) / dg.RATE_HZ
        t[samples // 2 :] += dg.GAP_S
        effects = {"time_delay": {"delay_s": 0.02}, "viscous_friction": {"delta": np.r_[2.0, np.zeros(model.n - 1)]}}
        q, v, a, tau = dg.true_torque(model, traj, t, effects=effects)
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


LOG_SAMPLES = (750, 1500, 3000, 6000)
LOG_COUNTS = (2, 3, 4, 6)


def scaling(quick: bool = False, out=None) -> dict:
    """Diagnosis time (wall, CPU; momentum form, no acceleration) vs log length (3 logs) and vs
    number of logs (1 500 samples each); the last log is the check log, the rest fit logs."""
    model = load_robot()
    lengths, counts = ((500, 1000), (2, 3)) if quick else (LOG_SAMPLES, LOG_COUNTS)
    size = 500 if quick else 1500

    def one(count, samples):
        logs = logs_3x1500(model, 0, False, count=count, samples=samples)
        d, wall, cpu = timed(lambda: dg.diagnose(model, logs[:-1], logs[-1:]))
        return {"logs": count, "samples": samples, "wall_s": wall, "cpu_s": cpu, "cause": d.result["cause"]}

    result = {"load_average": load_average()}
    result["vs_samples"] = {str(k): one(3, k) for k in lengths}
    result["vs_logs"] = {str(k): one(k, size) for k in counts}
    for name, xs, label in (("vs_samples", lengths, "samples per log (3 logs)"), ("vs_logs", counts, "logs")):
        rows = result[name].values()
        result[f"plot_{name}"] = plot(
            png(out, f"diagnose_{name}"),
            list(xs),
            {"wall": [r["wall_s"] for r in rows], "CPU": [r["cpu_s"] for r in rows]},
            label,
            "diagnosis time [s]",
            f"gap diagnosis time vs {label.split()[0]}",
        )
    return result


def real_leave_one_out():
    if not (REAL / "run1.csv").is_file() or not REFERENCE_URDF.is_file():
        return {"skipped": f"{REAL} or {REFERENCE_URDF} not available"}
    model = load_robot(model_path=REFERENCE_URDF)
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


def run(quick: bool = False, out=None) -> dict:
    out_dir = out
    out = {"timing_3x1500": timing_3x1500(), "target_time_s": 10.0}
    out["scaling"] = scaling(quick, out_dir)
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
