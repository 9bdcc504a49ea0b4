"""`safesysid run SCENARIO --arm lcm`: Algorithm 2 in wall-clock time against an arm over LCM.

The same diagram as the simulated-clock run (app/online.py build_online) with the station
swapped for LCM interface systems (systems/hardware/lcm_arm.py), the planner and estimator
calls in a worker process (systems/hardware/background.py), paced by the Simulator at real time.
The 1 kHz loop (controller, status in, command out) stays in this process, or, with
arm.control_loop arm, runs beside the arm on the plans sent to it (docs/hardware.md compares the
two). With a task, the task phase follows (app/task_lcm.py): the payload's release is a
gripper message the arm side applies. The referee is the arm's (`safesysid arm-sim`'s
arm_summary.json); lcm_run.json says what the run saw and how well it kept time.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import resource
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from safesysid.systems import config, methods
from safesysid.systems.config import Scenario

if TYPE_CHECKING:
    from pydrake.geometry import Meshcat
    from pydrake.systems.framework import Context
    from safesysid.online_diagram import OnlineDiagram
    from safesysid.systems.hardware.background import BackgroundWorker

SWITCH_INTERVAL_S = 1e-4
CHUNK_S = 0.05  # the run advances in chunks of this much, measuring its lag behind the wall clock


def _pace(sim, ctx, end_s: float) -> dict:
    """Advance to end_s at real time; how far the loop fell behind the wall clock [s]."""
    wall0, cpu0 = time.perf_counter(), time.process_time()
    lags, times = [], []
    while ctx.get_time() < end_s - 1e-9:
        sim.AdvanceTo(min(end_s, ctx.get_time() + CHUNK_S))
        times.append(ctx.get_time())
        lags.append(time.perf_counter() - wall0 - times[-1])
    lag = np.asarray(lags) - (lags[0] if lags else 0.0)
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return {
        "wall_time_s": time.perf_counter() - wall0,
        "max_lag_s": float(lag.max(initial=0.0)),
        "max_lag_at_s": float(times[int(np.argmax(lag))]) if lags else None,  # the run's clock at the end of that chunk
        "cpu_time_s": usage.ru_utime + usage.ru_stime,  # the whole process, set-up included
        "loop_cpu_time_s": time.process_time() - cpu0,  # this process while paced (every thread)
    }


def _estimate(est, ctx):
    history = est.history(est.GetMyContextFromRoot(ctx))
    if not history:
        return None, history
    last = history[-1]
    return {k: list(np.asarray(last[k], float)) for k in ("nominal", "lower", "upper")}, history


def run_wallclock(
    scenario: Scenario,
    out_dir: str | Path,
    method: str | None = None,
    *,
    seed: int | None = None,
    fifo: bool = True,
    meshcat: Meshcat | None = None,
) -> dict:
    """Run Algorithm 2's identification phase (and the task phase) against the arm on scenario.arm's channels."""
    from pydrake.systems.analysis import Simulator
    from safesysid.online import build_online
    from safesysid.summary import merge_events
    from safesysid.systems.hardware.background import BackgroundWorker
    from safesysid.systems.hardware.realtime import request_realtime
    from safesysid.task_lcm import run_task_lcm

    method = method or scenario.method
    seed = scenario.seed if seed is None else seed
    scenario = wallclock_planner(scenario)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    worker = BackgroundWorker(realtime=fifo)
    try:
        built = build_online(scenario, method, meshcat=meshcat, seed=seed, worker=worker)
        sim = Simulator(built.diagram)
        sim.set_target_realtime_rate(1.0)
        ctx = sim.get_mutable_context()
        _wait_for_arm(built.arm, scenario)
        worker.start()  # every system is registered: the forks inherit them
        sim.Initialize()
        sender = built.arm.plan_sender  # arm.control_loop arm: no controller evaluated here
        if sender is None:
            _warm_up(built, ctx)
        built.arm.receiver.rearm(ctx)
        gc.collect()
        gc.freeze()  # the set-up's objects out of the collector: a full collection stalls the loop
        gc.disable()  # and none while the loop runs: the objects it keeps made each one longer (tens of ms)
        sys.setswitchinterval(SWITCH_INTERVAL_S)  # the worker's result thread must not hold the loop 5 ms
        # Real-time from here: a set-up of seconds (the first plan) at SCHED_FIFO took the CPU
        # from the arm's loop on this machine (it fell ~180 ms behind its clock, then caught up).
        scheduling = (
            request_realtime() if fifo else {"scheduler": "normal", "warning": "real-time scheduling not asked"}
        )
        sim.ResetStatistics()  # real-time pacing from here, not from before the set-up
        _trace_stalls(sim, out)
        worker.clock_started()
        if sender is not None:  # the run's clock starts now: where it is on the arm's
            sender.start_clock(_arm_time(built.arm), ctx.get_time())
        spec = methods.method_spec(method)
        horizon = config.excitation_duration_s(spec, scenario) or config.planner_horizon_s(scenario)
        task = None
        if built.source is not None:  # the task phase, the release over LCM (app/task_lcm.py)
            task, timing = run_task_lcm(built, sim, scenario, method=method, pace=_pace)
        else:  # one more t_p: the estimator's last update (its samples end at the horizon) is published then
            timing = _pace(sim, ctx, horizon + scenario.planner.replan_period_s + scenario.plant.time_step_s)
        if sender is None:  # beside the arm the controller finishes the last plan at rest and holds
            _request_hold(built.arm, ctx.get_time())
    finally:
        worker.shutdown()
        _stop_stall_trace()
    summary = wallclock_summary(built, ctx, scenario, method=method, seed=seed, worker=worker)
    summary.update(timing=timing, scheduling=scheduling, identification_end_s=horizon)
    if task is not None:
        summary.update(task=task, events=summary["events"] + task["events"])
    summary["events"] = merge_events(summary["events"])
    (out / "lcm_run.json").write_text(json.dumps(summary, indent=2, default=float))
    return summary


STALL_TRACE_ENV = "SAFESYSID_STALL_TRACE"  # a step longer than this many ms dumps every thread's stack


def _trace_stalls(sim, out: Path) -> None:
    """With SAFESYSID_STALL_TRACE=MS: a step of the loop longer than MS ms writes every thread's
    Python stack to out/stalls.txt (faulthandler's timer, re-armed by the Simulator's monitor at
    each step: it needs no GIL). A stall of the whole process (the kernel's real-time cap) writes
    nothing (docs/hardware.md)."""
    import faulthandler
    import os

    limit_ms = os.environ.get(STALL_TRACE_ENV)
    if not limit_ms:
        return
    from pydrake.systems.framework import EventStatus

    trace = (out / "stalls.txt").open("w")

    def rearm(_context) -> EventStatus:
        faulthandler.dump_traceback_later(float(limit_ms) * 1e-3, file=trace)
        return EventStatus.DidNothing()

    sim.set_monitor(rearm)


def _stop_stall_trace() -> None:
    import faulthandler

    faulthandler.cancel_dump_traceback_later()  # its timer must not outlive the run (nor its file)


def wallclock_planner(scenario: Scenario) -> Scenario:
    """The planner's wall-time budget (planner.max_solve_time_s inside t_p): in wall-clock time an
    iteration budget has no bound on a call's duration, and a call past t_p is a missed deadline."""
    return dataclasses.replace(scenario, planner=dataclasses.replace(scenario.planner, budget="wall_time"))


def _wait_for_arm(arm, scenario: Scenario) -> None:
    """The arm's first status, or ArmNotAnswering after lcm_arm.FIRST_STATUS_TIMEOUT_S."""
    from safesysid.systems.hardware.lcm_arm import FIRST_STATUS_TIMEOUT_S

    deadline = time.monotonic() + FIRST_STATUS_TIMEOUT_S
    while not arm.statuses.count:
        if time.monotonic() > deadline:
            channel = scenario.arm.status_channel
            raise ArmNotAnswering(f"arm.status_channel {channel!r}: no status in {FIRST_STATUS_TIMEOUT_S:g} s")
        arm.statuses.receive(100)


def _arm_time(arm) -> float:
    """The arm's clock in its newest status [s] (the set-up's statuses taken in and dropped, as
    the receiver's rearm does: the estimator starts with the clock)."""
    from safesysid.systems.hardware.messages import parse_status

    arm.statuses.receive()
    arm.statuses.drain()
    return parse_status(arm.statuses.message(), arm.robot.n).t_s


def _warm_up(built, ctx) -> None:
    """Evaluate the command once (compiles the controller's kernels) before the clock starts."""
    port = built.controller.GetOutputPort("torque")
    port.Eval(port.get_system().GetMyContextFromRoot(ctx))


class ArmNotAnswering(RuntimeError):
    pass


def _request_hold(arm, t_s: float) -> None:
    """The run is over: ask the driver to hold (a few times: LCM is best effort)."""
    from safesysid.systems.hardware.messages import command_message

    msg = command_message(t_s + arm.time_step, np.zeros(arm.robot.n), hold=True).encode()  # newer than the last
    for _ in range(5):
        arm.lcm.Publish(arm.command_channel, msg)
        time.sleep(0.002)


def wallclock_summary(
    built: OnlineDiagram, ctx: Context, scenario: Scenario, *, method: str, seed: int, worker: BackgroundWorker | None
) -> dict:
    from safesysid.systems.hardware.lcm_systems import with_events

    planner, est = built.planner, built.estimator
    records = planner.records(planner.GetMyContextFromRoot(ctx)) if planner is not None else []
    events = list(built.arm.fault_events(ctx))
    if planner is not None:
        events += planner.events(planner.GetMyContextFromRoot(ctx))
    estimate, history = (None, []) if est is None else _estimate(est, ctx)
    if est is not None:
        events += est.events(est.GetMyContextFromRoot(ctx)) + getattr(est, "events_late", [])
    period = scenario.planner.replan_period_s
    planner_latency = list(getattr(planner, "latencies_s", []))
    estimator_latency = list(getattr(est, "latencies_s", []))
    return {
        "scenario": scenario.name,
        "method": method,
        "seed": seed,
        "arm": {"driver": "lcm", "lcm_url": scenario.arm.lcm_url, "status_channel": scenario.arm.status_channel},
        "status_stream": with_events(built.arm.receiver.guard(built.arm.receiver.GetMyContextFromRoot(ctx))),
        "estimate": estimate,
        "sysid": {
            "updates": len(history),
            "update_time_s": [h["update_time_s"] for h in history],
            "skipped": [] if est is None else est.skipped(est.GetMyContextFromRoot(ctx)),
        },
        "planner": {
            "iterations": len(records),
            "status": [r["status"] for r in records],
            "solve_time_s": [r["solve_time_s"] for r in records],
            "deadline_s": period,
        },
        "latency": {
            "t_p_s": period,
            "planner_s": planner_latency,
            "estimator_s": estimator_latency,
            "within_t_p": float(np.mean(np.asarray(planner_latency + estimator_latency) <= period))
            if planner_latency + estimator_latency
            else None,
            # each collected call's CPU and duration in its worker (CPU / duration: its share of a core)
            "worker": {
                lane: {"cpu_s": [c for c, _ in times], "wall_s": [w for _, w in times]}
                for lane, times in (worker.job_times.items() if worker is not None else ())
            },
        },
        "events": events,
    }


def cmd_run_lcm(args: argparse.Namespace, scenario: Scenario, method: str) -> int:
    """`safesysid run --arm lcm`: one line of what the run saw; exit 1 when no arm answered."""
    scenario = dataclasses.replace(scenario, arm=dataclasses.replace(scenario.arm, driver="lcm"))
    meshcat = None
    if getattr(args, "meshcat", False):  # the live arm from the status messages (prints the URL)
        from safesysid.viz import start_meshcat

        meshcat = start_meshcat(True)
    try:
        summary = run_wallclock(scenario, args.out, method, seed=args.seed, fifo=not args.no_fifo, meshcat=meshcat)
    except ArmNotAnswering as err:
        print(f"safesysid run: {err}", file=sys.stderr)
        return 1
    est = summary["estimate"] or {"nominal": [np.nan], "lower": [np.nan], "upper": [np.nan]}
    print(
        f"{scenario.name} / {method} over LCM: plans {summary['planner']['status']}; mass {est['nominal'][0]:.3f} kg "
        f"in [{est['lower'][0]:.3f}, {est['upper'][0]:.3f}]; lag {summary['timing']['max_lag_s'] * 1e3:.1f} ms; "
        f"{len(summary['events'])} events (the referee's judgement: arm-sim's arm_summary.json)"
    )
    if "task" in summary:
        task = summary["task"]
        print(f"task: executed {task['executed']}, hold {task['hold']}, release at {task['release_time_s']:.2f} s")
    return 0
