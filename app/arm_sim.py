"""`safesysid arm-sim SCENARIO`: the simulated arm as a separate process behind LCM (docs/hardware.md).

The scenario's arm (every plant.effects, the payload, the obstacles) steps in wall-clock time and
speaks what a real driver speaks: it applies the commands of `arm.command_channel` as motor
torque, publishes its status on `arm.status_channel` every plant step with its own time stamp,
and holds (gravity + PD at the pose of the trip, latched) before the first command, on a hold
request, or when no new command arrived for arm.watchdog_ms. It keeps its own ground truth
(arm_log.csv) and its own referee (the SafetyMonitor on the links' geometry, the torque before
saturation); arm_summary.json is the judgement of a run driving it. With a placement task its
gripper (app/arm_gripper.py) releases the payload on the run's open command and the referee
judges the placement.
"""

from __future__ import annotations

import argparse
import gc
import json
import signal
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pydrake.systems.framework import Context, Diagram
    from safesysid.systems.config import Scenario
    from safesysid.systems.hardware.lcm_systems import ArmDriver
    from safesysid.systems.hardware.plan_follower import PlanFollower
    from safesysid.systems.plant.arm_plant import RealArm
    from safesysid.systems.plant.safety_monitor import SafetyMonitor

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
CHUNK_S = 0.01  # between chunks the gripper acts (the release) and reports its status: at 100 Hz


def build_arm_side(scenario: Scenario, seed: int | None = None) -> tuple:
    """The station, its driver, referee, loggers and gripper: (diagram, arm, driver, monitor, loggers, gripper)."""
    from pydrake.systems.framework import DiagramBuilder
    from pydrake.systems.primitives import LogVectorOutput
    from safesysid.arm_gripper import ArmGripper
    from safesysid.systems.config import task_enabled
    from safesysid.systems.hardware.lcm_arm import add_arm_driver, make_lcm
    from safesysid.systems.plant.safety_monitor import SafetyMonitor
    from safesysid.systems.plant.station import add_real_arm

    builder = DiagramBuilder()
    # With a placement task the payload can be released (the gripper, app/arm_gripper.py).
    arm = add_real_arm(builder, scenario, seed=seed, releasable=task_enabled(scenario) and not scenario.task.goal_q_rad)
    lcm = make_lcm(scenario)
    if scenario.arm.control_loop == "arm":
        driver, torque = _add_controller_beside_the_arm(builder, arm, scenario, lcm=lcm)
    else:
        driver = add_arm_driver(builder, arm, scenario, lcm=lcm)
        torque = driver.get_output_port()
    h = scenario.plant.time_step_s
    ignore = [arm.released_body] if arm.released_body is not None else []
    # The referee judges the log afterwards (safety_monitor.judge_log): not in the 1 kHz loop.
    monitor = builder.AddNamedSystem(
        "referee", SafetyMonitor(arm.plant, arm.scene_graph, arm.robot, period_s=None, ignore_bodies=ignore)
    )
    builder.Connect(arm.query_output, monitor.query_port)
    builder.Connect(arm.plant_state_output, monitor.state_port)
    builder.Connect(arm.motor_torque_output, monitor.torque_port)
    builder.Connect(torque, monitor.command_port)
    loggers = {
        "state": LogVectorOutput(arm.state_output, builder, h),
        "measured_torque": LogVectorOutput(arm.measured_torque_output, builder, h),
        "command": LogVectorOutput(torque, builder, h),
        "true_state": LogVectorOutput(arm.plant_state_output, builder, h),
        "motor_torque": LogVectorOutput(arm.motor_torque_output, builder, h),
    }
    return builder.Build(), arm, driver, monitor, loggers, ArmGripper(scenario, arm, driver, lcm=lcm)


def _add_controller_beside_the_arm(builder, arm: RealArm, scenario: Scenario, *, lcm) -> tuple:
    """`arm.control_loop: arm`: the run's robust controller (the scenario's method's, on the same
    model and gains) here, on the plans of arm.plan_channel (PlanFollower: the task's curves too,
    the bare end effector's parameters from the payload's release on), and the status out.
    Returns (the follower, the controller's torque port: u before saturation, the referee's)."""
    from safesysid.closed_loop import add_controller
    from safesysid.online import prior
    from safesysid.online_diagram import THETA_NAMES
    from safesysid.systems import methods
    from safesysid.systems.hardware.lcm_arm import add_lcm_interface, add_plan_follower, add_status_publisher
    from safesysid.task_run import released_parameters

    add_lcm_interface(builder, lcm)
    theta0, box = prior(arm.robot, scenario, scenario.method)
    released = released_parameters(arm.robot, scenario, scenario.method) if arm.released_body is not None else None
    follower = add_plan_follower(builder, scenario, n=arm.robot.n, prior=(theta0, box.lo, box.hi), released=released)
    kind = methods.method_spec(scenario.method).first_controller
    controller, _ = add_controller(builder, arm, scenario, kind=kind)
    builder.Connect(follower.GetOutputPort("desired"), controller.GetInputPort("desired"))
    for name in THETA_NAMES:
        builder.Connect(follower.GetOutputPort(name), controller.GetInputPort(name))
    torque = controller.GetOutputPort("torque")
    add_status_publisher(builder, arm, scenario, lcm=lcm, commanded_torque=torque)
    return follower, torque


def run_arm_sim(
    scenario: Scenario, out_dir: str | Path, *, duration_s: float, seed: int | None = None, fifo: bool = True
) -> dict:
    """Serve the arm for duration_s of its clock (or until SIGINT/SIGTERM); write the judgement."""
    from pydrake.systems.analysis import Simulator
    from safesysid.systems.hardware.realtime import request_realtime

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scheduling = request_realtime() if fifo else {"scheduler": "normal", "warning": "real-time scheduling not asked"}
    diagram, arm, driver, monitor, loggers, gripper = build_arm_side(scenario, seed)
    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    arm.seed_noise(ctx)
    arm.set_state(ctx, np.asarray(scenario.q0_rad, float))
    sim.set_target_realtime_rate(1.0)
    stop = []
    for sig in STOP_SIGNALS:
        signal.signal(sig, lambda *_: stop.append(True))
    sim.Initialize()
    gc.collect()
    gc.freeze()  # the set-up's objects out of the collector: a full collection stalls the loop
    gc.disable()  # and none while the loop runs: the objects it keeps made each one longer (tens of ms)
    (out / "ready").write_text("")  # the arm answers from here on
    wall0 = time.perf_counter()
    while ctx.get_time() < duration_s and not stop:
        sim.AdvanceTo(min(duration_s, ctx.get_time() + CHUNK_S))
        gripper.step(ctx)
    wall = time.perf_counter() - wall0
    referee = judge_run(diagram, arm, monitor, loggers, ctx, released_at=gripper.t_release)
    summary = arm_summary(ctx, arm, driver, referee=referee, loggers=loggers, out=out)
    summary.update(gripper.judgement(ctx, safe=summary["safe"]))
    summary.update(scheduling=scheduling, wall_time_s=wall, arm_time_s=ctx.get_time(), stopped_by_signal=bool(stop))
    (out / "arm_summary.json").write_text(json.dumps(summary, indent=2, default=float))
    return summary


def judge_run(
    diagram: Diagram, arm: RealArm, monitor: SafetyMonitor, loggers: dict, ctx: Context, *, released_at: float | None
) -> dict:
    """The referee's judgement of the logged run, on a fresh context of the same diagram (the
    payload let go at released_at, as the run's context did: judge_log)."""
    from safesysid.systems.plant.safety_monitor import judge_log

    log = {name: loggers[key].FindLog(ctx) for name, key in _REFEREE_LOGS.items()}
    data = {name: entry.data().T for name, entry in log.items()}
    data["t"] = log["command"].sample_times()
    return judge_log(monitor, arm, diagram.CreateDefaultContext(), data, released_at=released_at).summary()


# judge_log's names -> the loggers'
_REFEREE_LOGS = {
    "state": "true_state",
    "motor_torque": "motor_torque",
    "command": "command",
}


def arm_summary(
    ctx: Context, arm: RealArm, driver: ArmDriver | PlanFollower, *, referee: dict, loggers: dict, out: Path
) -> dict:
    """The referee's judgement and the driver's record; the ground truth into out/arm_log.csv."""
    from safesysid.joint_log import write_joint_log
    from safesysid.systems.model.joint_data import JointLog

    n = arm.robot.n
    data = {name: sink.FindLog(ctx) for name, sink in loggers.items()}
    t = data["state"].sample_times()
    state, tau, u = (data[k].data().T for k in ("state", "measured_torque", "command"))
    write_joint_log(
        out / "arm_log.csv", JointLog(t, state[:, :n], state[:, n:], tau), {f"u{k + 1}": u[:, k] for k in range(n)}
    )
    guard = driver.guard(driver.GetMyContextFromRoot(ctx))
    from safesysid.systems.hardware.plan_follower import PlanFollower

    plans = None
    if isinstance(driver, PlanFollower):  # the controller beside the arm: the plans it took
        taken = driver.following(driver.GetMyContextFromRoot(ctx))
        plans = {"taken": len(taken.margins_s), "refused": len(taken.refused), "margin_s": list(taken.margins_s)}
    return {
        "plans": plans,
        "referee": referee,
        "safe": referee["collisions"] == 0 and referee["max_commanded_torque_ratio"] <= 1.0,
        "driver": {
            "holding": guard.tripped,
            "commands_received": guard.armed,
            "ignored_messages": guard.ignored,
            "events": list(guard.events),
        },
        "payload_true": {"theta": arm.true_theta()[arm.robot.ee_slice].tolist()},
    }


def cmd_arm_sim(args: argparse.Namespace) -> int:
    from safesysid.run_cli import _scenario

    scenario = _scenario(args)
    summary = run_arm_sim(scenario, args.out, duration_s=args.duration, seed=args.seed, fifo=not args.no_fifo)
    print(f"arm-sim: {'safe' if summary['safe'] else 'UNSAFE'}; referee {summary['referee']}")
    if summary["placement"] is not None:
        print(f"arm-sim: task {'succeeded' if summary['success'] else 'FAILED'}; placement {summary['placement']}")
    return 0
