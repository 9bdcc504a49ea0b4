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
from safesysid.systems.planner.trajectory_source import Piece

N, P = 3, 4
Q0 = np.array([0.1, -0.2, 0.3])
PRIOR = (np.full(P, 1.0), np.full(P, 0.5), np.full(P, 1.5))


def _thetas(scale):
    return (np.full(P, 1.0), np.full(P, 1.0 - scale), np.full(P, 1.0 + scale))


def _plan(t_start, q0, v0, a0, *, duration=0.4, scale=0.25, move=0.2):
    curve = QuinticBezier(np.array(q0, float), np.array(v0, float), np.array(a0, float), duration)
    return Plan(Piece(t_start, curve, np.asarray(q0, float) + move), _thetas(scale))


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

    def run(script):
        channel = _Channel()
        follower = PlanFollower(
            N, LatestMessage(channel, "PLAN", lcmt_drake_signal, backlog=64), time_step_s=0.001, q_start=Q0, prior=PRIOR
        )
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
        sim.AdvanceTo(1.2)
        state = follower.following(follower.GetMyContextFromRoot(ctx))
        return {k: (v.FindLog(ctx).sample_times(), v.FindLog(ctx).data().T) for k, v in logs.items()}, state, follower

    return run


def test_the_arm_takes_a_plan_only_new_early_and_continuous(follower_run):
    a = _plan(0.1, Q0, np.zeros(N), np.zeros(N))  # from rest at the start pose
    jump = _plan(0.3, Q0 + 0.05, np.zeros(N), np.zeros(N))  # not where a is at 0.3
    late = _after(a, 0.35)  # continuous, but it arrives at 0.4
    d = _after(a, 0.8)
    script = [(0.05, a), (0.06, a), (0.2, jump), (0.4, late), (0.7, d), (0.75, d)]
    logs, state, _ = follower_run(script)
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
