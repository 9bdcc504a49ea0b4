"""The 1 kHz loop across the process boundary, measured at the arm side (docs/hardware.md).

`python -m safesysid.benchmarks.lcm_loop [--seconds 60] [--control-loop arm|run] [--no-fifo] [--out DIR]`:
starts `safesysid arm-sim` and `safesysid run --arm lcm` on quickstart with enough plans for the
identification phase to last --seconds (the planner busy all along), and observes, in this process
beside the arm, the arrival time of every command (the controller in the run: the torque the arm
applies) and of every status (the arm's own loop: with the controller beside the arm, the period
at which its torque is applied): period p50/p99/max and the share of gaps over 2 ms; then the
planner's and estimator's latency against t_p and the workers' CPU (lcm_run.json), the plans the
arm took and their margins before their start (arm_summary.json) and the load average.
Not a timed test: the numbers depend on the machine and on what else runs on it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np

SCENARIO = Path(__file__).resolve().parents[1] / "scenarios" / "quickstart.yaml"
GAP_S = 0.002
OBSERVER_PRIORITY = 60  # above the loops (50): it waits in HandleSubscriptions between arrivals


def period_stats(arrivals_s: np.ndarray) -> dict:
    """Command period statistics from arrival times [s]."""
    gaps = np.diff(np.asarray(arrivals_s, float))
    if not len(gaps):
        return {"commands": int(len(arrivals_s))}
    return {
        "commands": int(len(arrivals_s)),
        "p50_ms": float(np.percentile(gaps, 50) * 1e3),
        "p99_ms": float(np.percentile(gaps, 99) * 1e3),
        "max_ms": float(gaps.max() * 1e3),
        "gaps_over_2ms_percent": float(np.mean(gaps > GAP_S) * 100),
    }


def _observe(arrivals: dict[str, list], url: str, stop: threading.Event) -> None:
    from safesysid.systems.hardware.queued_lcm import QueuedLcm
    from safesysid.systems.hardware.realtime import request_realtime

    request_realtime(OBSERVER_PRIORITY)  # this thread only: the observer must not be what is late

    lcm = QueuedLcm(url)  # every message of a burst, as the arm's driver receives them
    for channel, times in arrivals.items():
        lcm.Subscribe(channel, lambda _data, times=times: times.append(time.perf_counter()))
    while not stop.is_set():
        lcm.HandleSubscriptions(50)


def measure(seconds: float, out: Path, *, fifo: bool = True, control_loop: str = "arm") -> dict:
    from safesysid.systems.config import Arm

    tag = uuid.uuid4().hex[:8]
    command, status = f"BENCH_CMD_{tag}", f"BENCH_STATUS_{tag}"
    plans = max(2, math.ceil((seconds - 3.0) / 1.5) + 1)  # (plans - 1) t_p + t_f >= seconds
    arm_text = f"command_channel: {command}, status_channel: {status}, plan_channel: BENCH_PLAN_{tag}"
    text = [
        "--scenario-text",
        f"arm: {{{arm_text}, control_loop: {control_loop}}}",
        "--scenario-text",
        f"planner: {{num_plans: {plans}}}",
        "--scenario-text",  # a minute of data: the estimator's LP on a window, its update's cost bounded
        "estimator: {set_membership_window_s: 3.0}",
    ]
    flags = [] if fifo else ["--no-fifo"]
    cli = [sys.executable, "-m", "safesysid.cli"]
    arm = subprocess.Popen(
        [*cli, "arm-sim", str(SCENARIO), "--out", str(out / "arm"), "--duration", "100000", *flags, *text]
    )
    while not (out / "arm" / "ready").exists():
        time.sleep(0.2)
    arrivals, stop = {command: [], status: []}, threading.Event()
    observer = threading.Thread(target=_observe, args=(arrivals, Arm().lcm_url, stop))
    observer.start()
    run = subprocess.run([*cli, "run", str(SCENARIO), "--arm", "lcm", "--out", str(out / "run"), *flags, *text])
    stop.set()
    observer.join()
    arm.send_signal(subprocess.signal.SIGINT)
    arm.wait()
    lcm_run = json.loads((out / "run" / "lcm_run.json").read_text())
    arm_summary = json.loads((out / "arm" / "arm_summary.json").read_text())
    return {
        "seconds": seconds,
        "run_exit": run.returncode,
        "control_loop": control_loop,
        "command_period": period_stats(np.array(arrivals[command])),
        "status_period": period_stats(np.array(arrivals[status])),
        "plans_at_the_arm": arm_summary.get("plans"),
        "latency": lcm_run["latency"],
        "planner_status": lcm_run["planner"]["status"],
        "events": [e["kind"] for e in lcm_run["events"]],
        "scheduling": {"run": lcm_run["scheduling"], "arm": arm_summary["scheduling"]},
        "arm_safe": arm_summary["safe"],
        "arm_holding": arm_summary["driver"]["holding"],
        "load_average": os.getloadavg(),
        "run_cpu_time_s": lcm_run["timing"]["cpu_time_s"],
        "run_loop_cpu_time_s": lcm_run["timing"]["loop_cpu_time_s"],
        "run_wall_time_s": lcm_run["timing"]["wall_time_s"],
        "arm_wall_time_s": arm_summary["wall_time_s"],
        "arm_time_s": arm_summary["arm_time_s"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--no-fifo", action="store_true")
    parser.add_argument("--control-loop", choices=("arm", "run"), default="arm", help="where the controller runs")
    parser.add_argument("--out", default="out/lcm_loop")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = measure(args.seconds, out, fifo=not args.no_fifo, control_loop=args.control_loop)
    (out / "lcm_loop.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
