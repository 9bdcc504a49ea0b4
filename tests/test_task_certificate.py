"""The task phase is certified, slower, or refused (app/task_run.certify_task): ARMOUR's torque
certificate of the task with the parameter box latched at the switch must be <= 1; else the same
path is played slower, at the smallest scale of the grid up to task.max_time_scale that
certifies; else the task is refused (failure task_uncertified) and the arm holds. The box is
frozen at the switch (systems/trajectory_source.TaskPhaseSource)."""

import numpy as np
import pytest
import test_task_phase
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import BasicVector, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource
from safesysid.online import run_online
from safesysid.systems import methods
from safesysid.systems.model import parameter_sources
from safesysid.systems.model.loading import robot_from_scenario
from safesysid.systems.planner.trajectory_source import TaskPhaseSource
from safesysid.systems.task import phase as task_phase
from safesysid.systems.task.check import (
    certified_torque_ratio,
    phase_certificate,
    smallest_certified_scale,
    time_scale_grid,
)
from safesysid.task_run import certify_task
from test_task_phase import NARROWED_PRIOR, experiment_a

cache = test_task_phase.cache  # its task-trajectory cache (a session fixture: one solve for both files)


def test_the_smallest_certified_scale_of_the_grid_is_taken_whatever_the_certificates_order():
    assert time_scale_grid(3.0, 0.25) == pytest.approx([1 + 0.25 * k for k in range(9)])
    assert time_scale_grid(2.1, 0.5) == pytest.approx([1.0, 1.5, 2.0, 2.1])  # the cap itself is tried
    assert time_scale_grid(1.0, 0.25) == [1.0]
    # not monotone: 1.5 is worse than 1.25, 2.0 worse than 1.75
    certificate = {1.0: 1.3, 1.25: 1.05, 1.5: 1.1, 1.75: 0.97, 2.0: 1.02, 2.25: 0.9}.__getitem__
    found = smallest_certified_scale(certificate, [2.25, 2.0, 1.75, 1.5, 1.25, 1.0])
    assert found.certified and found.time_scale == 1.75 and found.ratio == 0.97
    assert [s for s, _ in found.tried] == [1.0, 1.25, 1.5, 1.75]
    refused = smallest_certified_scale(certificate, [1.0, 1.25, 1.5, 2.0])
    assert not refused.certified and refused.time_scale is None and refused.ratio == 1.02


def test_a_certificate_above_one_is_played_slower_on_the_same_path_until_it_holds(cache):
    scene = experiment_a(cache, NARROWED_PRIOR)
    problem, plan = task_phase.task_plan(scene)
    theta0, box = parameter_sources.task_parameters(
        methods.method_spec("conservative"), robot_from_scenario(scene), scene
    )
    thetas = (theta0, box.lo, box.hi)
    curves, report, text = certify_task(problem, [plan.trajectory], thetas, task=scene.task)
    (played,) = curves
    scale = report["time_scale"]
    assert report["certified_torque_ratio_unscaled"] > 1.0 and 1.0 < scale <= scene.task.max_time_scale
    assert f"{scale:g}x slower" in text and not report["uncertified"]
    assert played.duration == pytest.approx(scale * plan.trajectory.duration)
    assert np.array_equal(played.control_points, plan.trajectory.control_points)  # the same path
    # What is played, certified again from scratch: within the limit; one grid step faster is not.
    assert certified_torque_ratio(problem, played, *thetas)[0] <= 1.0
    assert phase_certificate(problem, [plan.trajectory], thetas, scale=scale - scene.task.time_scale_step) > 1.0


def test_a_task_that_no_scale_up_to_the_cap_certifies_is_refused_and_the_arm_holds(cache):
    """conservative in experiment (a): Table II's box certifies 1.32 at 1x, 1.07 at 3x (gravity and
    the tube dominate): refused, the arm holds q0 (never released), a failed run."""
    scene = experiment_a(cache)
    s = run_online(scene, None, method="conservative", write=False)
    task = s["task"]
    assert s["failure"] == "task_uncertified" and s["phase"] == "task" and not s["success"], s["events"]
    assert task["uncertified"] and not task["executed"] and task["time_scale"] is None and task["duration_s"] is None
    assert task["certified_torque_ratio"] > 1.0 and task["certificate_box_contains_payload"]
    assert task["time_scales_tried"][-1][0] == scene.task.max_time_scale
    kinds = [e["kind"] for e in s["events"]]
    assert "task_uncertified" in kinds and "task_start" not in kinds and "release" not in kinds
    assert s["max_velocity_ratio"] < 0.01 and s["collisions"] == 0 and s["max_commanded_torque_ratio"] < 1.0


class SteppedBox(LeafSystem):
    """A parameter box that changes at t_change (an estimator updating after the switch)."""

    def __init__(self, size, t_change):
        super().__init__()
        self.DeclareVectorOutputPort(
            "box", BasicVector(size), lambda c, out: out.SetFromVector(np.full(size, 2.0 + (c.get_time() >= t_change)))
        )


def test_the_box_latched_at_the_switch_stays_frozen_when_its_source_changes_afterwards():
    n, p, switch = 7, 14 * 7, 0.5
    latched = []

    def make_task(q_now, thetas):
        latched.append(thetas)
        return [], [], {}  # no curves: the arm holds, the parameters are still the task's

    builder = DiagramBuilder()
    src = builder.AddSystem(TaskPhaseSource(n, p, np.zeros(n), switch_time_s=switch, make_task=make_task))
    plan = {
        "plan_desired": np.zeros(3 * n),
        **{f"plan_{k}": np.ones(p) for k in ("theta0", "theta_lower", "theta_upper")},
    }
    for name, value in plan.items():
        builder.Connect(builder.AddSystem(ConstantVectorSource(value)).get_output_port(), src.GetInputPort(name))
    live = builder.AddSystem(SteppedBox(p, t_change=0.7))
    for name in ("theta0", "theta_lower", "theta_upper"):
        builder.Connect(live.get_output_port(), src.GetInputPort(f"task_{name}"))
    sim = Simulator(builder.Build())
    sim.Initialize()
    sim.AdvanceTo(1.0)
    ctx = src.GetMyContextFromRoot(sim.get_context())
    assert np.all(src.GetInputPort("task_theta_upper").Eval(ctx) == 3.0)  # the source did change
    for name in ("theta0", "theta_lower", "theta_upper"):
        assert np.all(src.GetOutputPort(name).Eval(ctx) == 2.0), name  # the controller keeps the latched box
    assert len(latched) == 1 and all(np.all(x == 2.0) for x in latched[0])  # certified with that same box


def test_compare_table_shows_each_tasks_duration_scale_certificate_and_refusal(tmp_path):
    from safesysid.compare_cli import table, write_tables

    def run(method, task):
        return dict(
            method=method, dumbbell="4lb", trial=0, success=task is not None, failure=None, collisions=0, task=task
        )

    played = dict(duration_s=2.5, time_scale=1.25, certified_torque_ratio=0.958, certificate_box_contains_payload=True)
    refused = dict(played, duration_s=None, time_scale=None, certified_torque_ratio=1.075, uncertified=True)
    blind = dict(played, duration_s=2.0, time_scale=1.0, certified_torque_ratio=0.371)
    blind["certificate_box_contains_payload"] = False
    done = [run("ours", played), run("conservative", refused), run("wrong", blind), run("grav-pid", None)]
    write_tables(
        tmp_path,
        "a",
        table(done, ["ours", "conservative", "wrong", "grav-pid"], ["4lb"], trials=1),
        dumbbells=["4lb"],
        trials=1,
    )
    md = (tmp_path / "table.md").read_text()
    assert "| ours | 2.50 s (1.25x, certificate 0.958) |" in md
    assert "| conservative | refused: task_uncertified (certificate 1.075 at the cap) |" in md
    assert "| wrong | 2.00 s (1x, certificate 0.371, box excludes the payload) |" in md
    assert "| grav-pid | not played |" in md


def test_a_task_without_a_certificate_reports_every_field_null_or_one(robot):
    """A PID or adaptive task (no certify_task report beyond its scale) and a task never found:
    the same summary keys as a certified one, null where there is nothing to say."""
    from safesysid.systems.planner.trajectory_source import PhaseState, TimedCurve
    from safesysid.task_run import task_certificate_summary

    truth = robot.theta.copy()
    box = (truth, truth - 1.0, truth + 1.0)
    curve = TimedCurve(0.0, test_task_phase.straight(np.zeros(7), np.ones(7), 2.0))
    pid = PhaseState("task", 0.0, np.zeros(7), (curve,), True, box, (), {"time_scale": 1.0})
    lost = PhaseState("task", 0.0, np.zeros(7), (), False, box, (), {})
    for st, scale, duration in ((pid, 1.0, 2.0), (lost, None, None)):
        s = task_certificate_summary(st, truth, robot)
        assert s["time_scale"] == scale and s["duration_s"] == duration and not s["uncertified"]
        assert s["certified_torque_ratio"] is None and s["certified_torque_ratio_unscaled"] is None
        assert s["time_scales_tried"] == [] and s["certificate_box_contains_payload"]
