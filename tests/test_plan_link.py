"""The controller beside the arm (arm.control_loop: arm): the plan message and the arm's
PlanFollower (systems/hardware/plan_message.py, plan_follower.py)."""

import numpy as np
import pytest
from drake import lcmt_drake_signal
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import VectorLogSink
from safesysid.systems.hardware.lcm_systems import LatestMessage
from safesysid.systems.hardware.plan_follower import PlanFollower
from safesysid.systems.hardware.plan_message import Plan, parse_plan, plan_message
from safesysid.systems.math.bezier import QuinticBezier
from safesysid.systems.math.piecewise_bezier import Parametrization, PiecewiseBezier
from safesysid.systems.planner.trajectory_source import Piece, TimedCurve

N, P = 3, 4
Q0 = np.array([0.1, -0.2, 0.3])
PRIOR = (np.full(P, 1.0), np.full(P, 0.5), np.full(P, 1.5))
RELEASED = (np.full(P, 0.2), np.full(P, 0.1), np.full(P, 0.3))  # the bare end effector's


def _thetas(scale):
    return (np.full(P, 1.0), np.full(P, 1.0 - scale), np.full(P, 1.0 + scale))


def _plan(t_start, q0, v0, a0, *, duration=0.4, scale=0.25, move=0.2):
    curve = QuinticBezier(np.array(q0, float), np.array(v0, float), np.array(a0, float), duration)
    return Plan(Piece(t_start, curve, np.asarray(q0, float) + move), _thetas(scale))


def _task_curve(t_start, q_start, q_goal, *, pieces=2, piece_s=0.15):
    """A rest-to-rest task curve (the task trajectory's form: systems/task/trajectory.py)."""
    par = Parametrization.make(pieces)
    z = np.random.default_rng(1).normal(scale=0.05, size=(par.r, N))
    points = par.control_points(z, q_start, q_goal).reshape(pieces, 6, N)
    return TimedCurve(t_start, PiecewiseBezier(points, piece_s))


def _after(plan, t):
    """The plan starting at t where `plan` is then (continuous)."""
    return _plan(t, *plan.piece.evaluate(t), scale=0.1, move=-0.1)


def test_a_plan_crosses_exactly_and_a_bad_one_is_not_a_plan():
    plan = _plan(2.5, Q0, [0.3, 0.0, -0.1], [1.0, 2.0, 3.0])
    back = parse_plan(lcmt_drake_signal.decode(plan_message(plan, sent_s=2.0).encode()), N)
    assert back.piece.t_start == 2.5 and back.piece.curve.duration == 0.4
    for t in (2.5, 2.6, 2.9, 3.2):  # the same doubles: the same trajectory, bit for bit
        assert all(np.array_equal(a, b) for a, b in zip(back.piece.evaluate(t), plan.piece.evaluate(t)))
    assert all(np.array_equal(a, b) for a, b in zip(back.thetas, plan.thetas))
    assert parse_plan(plan_message(plan, sent_s=2.0), N + 1) is None  # another arm
    lower = 2 + 4 * N + P  # where the lower bounds start
    for k, value in ((1, 0.0), (5, np.nan), (lower, 3.0)):  # no duration, a NaN, a lower bound above its upper
        msg = plan_message(plan, sent_s=2.0)
        msg.val[k] = value
        assert parse_plan(msg, N) is None, k


def test_a_task_curve_crosses_exactly_and_one_not_at_rest_at_its_end_is_not_a_plan():
    plan = Plan(_task_curve(2.5, Q0, Q0 - 0.3), _thetas(0.05), release=True)
    back = parse_plan(lcmt_drake_signal.decode(plan_message(plan, sent_s=2.0).encode()), N)
    assert isinstance(back.piece, TimedCurve) and back.release and back.piece.t_start == 2.5
    for t in (2.4, 2.5, 2.61, 2.7, 2.8, 2.9):
        assert all(np.array_equal(a, b) for a, b in zip(back.piece.evaluate(t), plan.piece.evaluate(t)))
        # the 1 kHz loop's evaluation is the task trajectory's own (to rounding)
        exact = plan.piece.curve.evaluate([t - 2.5], orders=2)
        assert all(np.allclose(a[0], b, rtol=0, atol=1e-10) for a, b in zip(exact, back.piece.evaluate(t)))
    assert all(np.array_equal(a, b) for a, b in zip(back.thetas, plan.thetas))
    assert not parse_plan(plan_message(Plan(plan.piece, plan.thetas), sent_s=2.0), N).release
    moving = plan.piece.curve.control_points.copy()
    moving[-1, -2] += 0.01  # the last piece no longer at rest at its end: the arm would jump there
    moving_plan = Plan(TimedCurve(2.5, PiecewiseBezier(moving, 0.15)), plan.thetas, release=True)
    assert parse_plan(plan_message(moving_plan, sent_s=2.0), N) is None
    for k, value in ((2, 0.0), (2, 1.5), (3, 0.5)):  # no pieces, a fraction of one, a release neither yes nor no
        msg = plan_message(plan, sent_s=2.0)
        msg.val[k] = value
        assert parse_plan(msg, N) is None, k


class _Channel:
    """DrakeLcm's receiving half for LatestMessage: messages put in by the test."""

    def __init__(self):
        self.handler, self.queue = None, []

    def Subscribe(self, channel, handler):  # noqa: N802 -- DrakeLcm's name
        self.handler = handler

    def HandleSubscriptions(self, timeout_ms):  # noqa: N802
        sent, self.queue = self.queue, []
        for data in sent:
            self.handler(data)
        return len(sent)


@pytest.fixture()
def follower_run():
    """Run a PlanFollower for 1.2 s with plans arriving at scripted times; (logs, follower state)."""

    def run(script, until=1.2):
        channel = _Channel()
        plans = LatestMessage(channel, "PLAN", lcmt_drake_signal, backlog=64)
        follower = PlanFollower(N, plans, time_step_s=0.001, q_start=Q0, prior=PRIOR, released=RELEASED)
        builder = DiagramBuilder()
        builder.AddSystem(follower)
        logs = {}
        for name in ("desired", "theta_lower"):
            port = follower.GetOutputPort(name)
            logs[name] = builder.AddSystem(VectorLogSink(port.size(), publish_period=0.001))
            builder.Connect(port, logs[name].get_input_port())
        diagram = builder.Build()
        sim = Simulator(diagram)
        ctx = sim.get_mutable_context()
        sim.Initialize()
        for t_arrive, plan in script:
            sim.AdvanceTo(t_arrive)
            channel.queue.append(plan_message(plan, sent_s=t_arrive).encode())
        sim.AdvanceTo(until)
        state = follower.following(follower.GetMyContextFromRoot(ctx))
        logged = {k: (v.FindLog(ctx).sample_times(), v.FindLog(ctx).data().T) for k, v in logs.items()}
        return logged, state, follower, sim

    return run


def test_the_arm_takes_a_plan_only_new_early_and_continuous(follower_run):
    a = _plan(0.1, Q0, np.zeros(N), np.zeros(N))  # from rest at the start pose
    jump = _plan(0.3, Q0 + 0.05, np.zeros(N), np.zeros(N))  # not where a is at 0.3
    late = _after(a, 0.35)  # continuous, but it arrives at 0.4
    d = _after(a, 0.8)
    script = [(0.05, a), (0.06, a), (0.2, jump), (0.4, late), (0.7, d), (0.75, d)]
    logs, state, *_ = follower_run(script)
    assert [e["kind"] for e in state.events] == ["plan_discontinuous", "plan_late"]  # the repeats: nothing
    assert state.last_start_s == 0.8 and len(state.margins_s) == 2 and min(state.margins_s) >= 0.04
    t, desired = logs["desired"]
    for time_s in (0.0, 0.05, 0.099):  # before the first plan: the start pose, at rest
        k = np.searchsorted(t, time_s)
        assert np.allclose(desired[k], np.concatenate([Q0, np.zeros(2 * N)]))
    for time_s in (0.2, 0.45, 0.79, 0.85, 1.1):  # a alone until 0.8 (jump and late refused), then d
        k = np.searchsorted(t, time_s)
        expected = (a if time_s < 0.8 else d).piece.evaluate(t[k])
        assert np.allclose(desired[k], np.concatenate(expected), atol=1e-12), time_s
    t, lower = logs["theta_lower"]
    # the parameters each plan was certified with, from its start (a log shows the value before the step's update)
    for time_s, expected in ((0.05, PRIOR[1]), (0.5, a.thetas[1]), (0.9, d.thetas[1])):
        assert np.array_equal(lower[np.searchsorted(t, time_s)], expected), time_s


def test_the_arm_follows_the_task_and_lets_the_payload_go_only_at_its_end(follower_run):
    """The task's curves are plans too; the gripper may open only at rest at the end of the one
    marked release, and from then on the controller has the bare end effector's parameters."""
    a = _plan(0.1, Q0, np.zeros(N), np.zeros(N))  # at rest at Q0 + 0.2 from 0.5
    task = Plan(_task_curve(0.6, Q0 + 0.2, Q0 - 0.1), _thetas(0.05), release=True)  # ends at 0.9
    _, state, follower, sim = follower_run([(0.05, a), (0.55, task), (0.56, task)], until=0.58)
    ctx = follower.GetMyMutableContextFromRoot(sim.get_mutable_context())
    assert state.events == () and len(state.margins_s) == 2
    assert "not on the task" in follower.release_refusal(ctx)
    sim.AdvanceTo(0.75)
    assert "not reached the end" in follower.release_refusal(ctx)
    desired = follower.GetOutputPort("desired").Eval(ctx)
    assert np.allclose(desired, np.concatenate(task.piece.evaluate(0.75)), rtol=0, atol=1e-12)
    assert np.array_equal(follower.GetOutputPort("theta_lower").Eval(ctx), task.thetas[1])
    sim.AdvanceTo(0.95)
    assert follower.release_refusal(ctx) is None
    follower.payload_released(ctx)
    sim.AdvanceTo(1.0)
    assert np.array_equal(follower.GetOutputPort("theta_lower").Eval(ctx), RELEASED[1])
    assert np.allclose(follower.GetOutputPort("desired").Eval(ctx)[:N], Q0 - 0.1, atol=1e-12)  # at rest at the end
    assert [e["kind"] for e in follower.following(ctx).events] == ["released_parameters"]


class _Sent:
    """DrakeLcm's sending half: what was published."""

    def __init__(self):
        self.data = []

    def Publish(self, channel, data):  # noqa: N802 -- DrakeLcm's name
        self.data.append(data)


def test_the_run_sends_the_task_curves_ahead_on_the_arms_clock_the_last_one_marked_release():
    from types import SimpleNamespace

    from safesysid.systems.hardware.plan_sender import PlanSender
    from safesysid.systems.planner.system import PlannerState
    from safesysid.systems.planner.trajectory_source import PhaseState

    first = _task_curve(0.02, Q0, Q0 + 0.1)
    second = _task_curve(first.t_end, Q0 + 0.1, Q0 - 0.1)
    lcm = _Sent()
    sender = PlanSender(SimpleNamespace(pending=None), lcm, "PLAN", lead_s=0.2)
    ctx = sender.CreateDefaultContext()
    sender.get_input_port(0).FixValue(ctx, PlannerState())
    waiting = PhaseState("task", 0.0, Q0, (first, second), False, _thetas(0.05))  # the worker still makes it
    sender.task.FixValue(ctx, waiting)
    sender.start_clock(arm_time_s=5.0, run_time_s=0.0)  # the arm's clock: the run's + 5.2 s (lead)

    sim = Simulator(sender, ctx)  # it publishes every 10 ms

    def sent_at(t):
        sim.AdvanceTo(t - 0.005)
        lcm.data.clear()
        sim.AdvanceTo(t + 0.005)
        return [parse_plan(lcmt_drake_signal.decode(d), N) for d in lcm.data]

    assert sent_at(0.01) == []
    sender.task.FixValue(ctx, PhaseState("task", 0.0, Q0, (first, second), True, _thetas(0.05)))
    plans = sent_at(0.02)
    assert [p.piece.t_start for p in plans] == pytest.approx([5.22, 5.52])
    assert [p.release for p in plans] == [False, True]
    assert all(np.array_equal(a, b) for p in plans for a, b in zip(p.thetas, _thetas(0.05)))
    assert np.array_equal(plans[1].piece.curve.control_points, second.curve.control_points)
    assert [p.piece.t_start for p in sent_at(0.3)] == pytest.approx([5.52])  # the first has started on the arm
