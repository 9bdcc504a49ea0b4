"""ExcitingPlanner LeafSystem: receding horizon, continuity across replans, braking on failure."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, VectorLogSink
from safesysid.systems.config import Planner
from safesysid.systems.controller import armour as ctl
from safesysid.systems.model.robot_model import load_robot
from safesysid.systems.planner.safe_planner import PlanResult, SafePlanner
from safesysid.systems.planner.system import ExcitingPlanner

Q0 = np.array([0.0, 0.26, 0.0, 2.0, 0.0, 0.9, 1.57])


@pytest.fixture(scope="module")
def setup():
    robot = load_robot(coulomb_smoothing=0.01)
    theta0 = robot.theta.copy()
    rel = 0.05 * np.abs(theta0)
    lo, hi = theta0 - rel, theta0 + rel
    gains = ctl.ArmourGains(Kr=np.array([5.0] * 4 + [7.0] * 3), alpha=20.0, V_max=0.02)
    planner = SafePlanner(
        robot,
        Planner(num_cost_samples=32),
        obstacles=[],
        payload=None,
        tracking=ctl.tracking_bounds_for(robot, gains, lo),
    )
    return robot, planner, (theta0, lo, hi)


def simulate(system, t_end, connect_thetas=None, consistent=None, theta_sources=None):
    """Run the planner alone; logs of q, v, a and (plan_theta0, lower, upper) every 5 ms.
    theta_sources: systems whose output feeds theta0, lower, upper (instead of constants)."""
    builder = DiagramBuilder()
    builder.AddSystem(system)
    if connect_thetas is not None:
        theta_sources = [ConstantVectorSource(value) for value in connect_thetas]
    for k, src in enumerate(theta_sources or []):
        builder.AddSystem(src)
        builder.Connect(src.get_output_port(), system.get_input_port(k))
    if consistent is not None:
        flag = builder.AddSystem(ConstantVectorSource([consistent]))
        builder.Connect(flag.get_output_port(), system.GetInputPort("estimate_consistent"))
    logs = []
    for name in ("q_desired", "v_desired", "a_desired", "plan_theta0", "plan_theta_lower", "plan_theta_upper"):
        port = system.GetOutputPort(name)
        log = builder.AddSystem(VectorLogSink(port.size(), publish_period=0.005))
        builder.Connect(port, log.get_input_port())
        logs.append(log)
    diagram = builder.Build()
    sim = Simulator(diagram)
    sim.AdvanceTo(t_end)
    ctx = sim.get_context()
    data = [log.FindLog(ctx) for log in logs]
    return system.planner_state(system.GetMyContextFromRoot(ctx)), data


def test_four_plans_continuous_desired_trajectory_ending_at_rest(setup):
    robot, planner, thetas = setup
    system = ExcitingPlanner(planner, Q0, *thetas)
    st, logs = simulate(system, 8.0, connect_thetas=thetas)
    assert st.calls == 4 and st.done
    assert [r["t_s"] for r in st.records] == pytest.approx([0.0, 1.5, 3.0, 4.5])
    assert all(r["ok"] for r in st.records)
    assert all(np.isfinite(r["solve_time_s"]) and r["status"] in ("solved", "best_feasible") for r in st.records)
    t = logs[0].sample_times()
    q, v, a = (log.data().T for log in logs[:3])
    # Continuity of q, qd (and qdd) across the replans: the next plan starts at the old state.
    dt = np.diff(t)
    assert np.max(np.abs(np.diff(q, axis=0))) < 1.5 * np.max(np.abs(v)) * dt.max() + 1e-9
    assert np.max(np.abs(np.diff(v, axis=0))) < 1.5 * np.max(np.abs(a)) * dt.max() + 1e-9
    # It moves, and the last plan (started at 4.5 s) is at rest from 7.5 s on.
    assert np.max(np.abs(q - Q0)) > 0.02
    late = t >= 7.5
    assert np.allclose(v[late], 0, atol=1e-12) and np.allclose(a[late], 0, atol=1e-12)
    assert np.allclose(q[late], st.plan.q_end)


class Wrapped:
    """The real planner `inner` seen through a wrapper: what the wrapper does not define is inner's
    (config, robot, executed_rows of planner.cumulative_excitation, ...)."""

    def __init__(self, inner):
        self.inner = inner

    def __getattr__(self, name):
        return getattr(self.inner, name)


def _solver_failure():
    return PlanResult(ok=False, status="solver_failed", reason="test")


def _exception():  # a bug or a numerical failure inside the call
    raise np.linalg.LinAlgError("SVD did not converge")


@pytest.mark.parametrize(
    "second_call, status, reason",
    [(_solver_failure, "solver_failed", "test"), (_exception, "planner_error", "LinAlgError: SVD did not converge")],
)
def test_failed_plan_keeps_the_previous_one_which_brakes(setup, second_call, status, reason):
    """The second call fails, by its result or by raising (that call's failure, logged with its
    text): the verified plan brakes, the simulation goes on."""
    robot, planner, thetas = setup

    class FailsSecond(Wrapped):
        """The real planner, except for its second call."""

        def __init__(self, inner):
            super().__init__(inner)
            self.calls = 0

        def plan(self, *args, **kw):
            self.calls += 1
            return second_call() if self.calls == 2 else self.inner.plan(*args, **kw)

    system = ExcitingPlanner(FailsSecond(planner), Q0, *thetas)
    st, logs = simulate(system, 5.0)  # theta ports unconnected: the constructor's values are used
    assert st.calls == 2 and st.done
    assert st.records[1]["braking"] and not st.records[1]["ok"]
    assert (st.records[1]["status"], st.records[1]["reason"]) == (status, reason)
    assert [(e["t"], e["kind"]) for e in st.events] == [(1.5, "plan_failed"), (1.5, "brake")]
    t = logs[0].sample_times()
    v = logs[1].data().T
    assert np.max(np.abs(v[t < 2.9])) > 1e-3  # moving along the first plan ...
    assert np.allclose(v[t >= 3.0], 0, atol=1e-12)  # ... which ends at rest at 3 s
    assert st.t_start == 0.0


def _changing_estimate(theta0, lo, hi, at_s=0.7):
    """Sources of (theta0, lower, upper): the given box, then from at_s a box half as wide (consistent)."""
    from pydrake.systems.primitives import TrajectorySource
    from pydrake.trajectories import PiecewisePolynomial

    tight = (theta0, theta0 - 0.5 * (theta0 - lo), theta0 + 0.5 * (hi - theta0))
    return [
        TrajectorySource(PiecewisePolynomial.ZeroOrderHold([min(at_s, 0.0) - 1.0, at_s, 10.0], np.stack([a, b, b], 1)))
        for a, b in zip((theta0, lo, hi), tight)
    ]


class FailsFrom(Wrapped):
    """The real planner until call `first_failure` (counted from 1); from then on each call fails."""

    def __init__(self, inner, first_failure):
        super().__init__(inner)
        self.first_failure, self.calls = first_failure, []

    def plan(self, q, v, a, theta0, lo, hi, **kw):
        self.calls.append(np.concatenate([theta0, lo, hi]))
        if len(self.calls) >= self.first_failure:
            return _solver_failure()
        return self.inner.plan(q, v, a, theta0, lo, hi, **kw)


@pytest.mark.parametrize("first_failure", [1, 2])
def test_a_failed_plan_never_switches_the_controller_to_a_new_consistent_estimate(setup, first_failure):
    """Guarantee 6: a consistent, tighter estimate arrives at 0.7 s and the planning call at 1.5 s
    fails (2): the braking plan keeps the parameters it was certified with to the end. Before any
    certified plan (1: the first call, at 0 s, fails and the arm holds q0) the controller keeps the
    constructor's parameters (the prior) and never takes the estimate no plan certified."""
    robot, planner, (theta0, lo, hi) = setup
    defaults = np.concatenate([theta0, lo, hi])
    failing = FailsFrom(planner, first_failure)
    system = ExcitingPlanner(failing, Q0, theta0, lo, hi)
    at_s = 0.7 if first_failure == 2 else -1.0  # (1): the first call already sees the tight box
    st, logs = simulate(system, 3.5, theta_sources=_changing_estimate(theta0, lo, hi, at_s=at_s))
    assert len(failing.calls) == first_failure and st.done
    assert not np.array_equal(failing.calls[-1], defaults)  # the failed call was asked with the new box
    out = np.hstack([log.data().T for log in logs[3:]])
    certified = defaults  # what the executing plan (or the hold before any plan) was certified with
    assert np.array_equal(out, np.broadcast_to(certified, out.shape))
    assert np.array_equal(np.concatenate(st.thetas), certified)


def test_infeasible_first_plan_holds_the_start(setup):
    robot, planner, thetas = setup

    class Never:
        config, robot = planner.config, planner.robot

        def plan(self, *args, **kw):
            return PlanResult(ok=False, status="infeasible_start", reason="start inside a margin")

    system = ExcitingPlanner(Never(), Q0, *thetas)
    st, logs = simulate(system, 2.0)
    assert st.plan is None and st.calls == 1 and st.done
    assert not st.records[0]["braking"] and st.records[0]["reason"] == "start inside a margin"
    assert [e["kind"] for e in st.events] == ["plan_failed"]  # nothing to brake on: it never moved
    assert np.allclose(logs[0].data().T, Q0) and np.allclose(logs[1].data(), 0)


class Recording(Wrapped):
    """The real planner, keeping the parameters each call was asked to certify."""

    def __init__(self, inner):
        super().__init__(inner)
        self.calls = []

    def plan(self, q, v, a, theta0, lo, hi, **kw):
        res = self.inner.plan(q, v, a, theta0, lo, hi, **kw)
        self.calls.append((np.concatenate([theta0, lo, hi]), res.ok))
        return res


def test_outputs_the_parameters_the_executing_plan_was_certified_with(setup):
    """The estimate tightens at 0.7 s: the plan started at 0 s keeps its own parameters on the
    output until the plan started at 1.5 s, certified with the tight box, takes over."""
    from pydrake.systems.primitives import TrajectorySource
    from pydrake.trajectories import PiecewisePolynomial

    robot, planner, (theta0, lo, hi) = setup
    tight = (theta0, theta0 - 0.5 * (theta0 - lo), theta0 + 0.5 * (hi - theta0))
    sources = [
        TrajectorySource(PiecewisePolynomial.ZeroOrderHold([0.0, 0.7, 10.0], np.stack([a, b, b], 1)))
        for a, b in zip((theta0, lo, hi), tight)
    ]
    recording = Recording(planner)
    system = ExcitingPlanner(recording, Q0, theta0, lo, hi, num_plans=2)
    st, logs = simulate(system, 3.0, theta_sources=sources)
    assert [ok for _, ok in recording.calls] == [True, True]
    t = logs[3].sample_times()
    out = np.hstack([log.data().T for log in logs[3:]])
    first, second = (params for params, _ in recording.calls)
    assert not np.array_equal(first, second)
    # A log at t shows the outputs before the updates at t (Drake publishes, then updates).
    before, after = t <= 1.5, t > 1.5
    assert np.array_equal(out[before], np.broadcast_to(first, out[before].shape))
    assert np.array_equal(out[after], np.broadcast_to(second, out[after].shape))
    assert np.array_equal(np.concatenate(st.thetas), second)


class InProcessWorker:
    """background.BackgroundWorker's interface, each job run at once in this process."""

    def __init__(self):
        self.job_times = {"planner": [], "estimator": []}

    def submit(self, fn, *args, lane):
        import time
        from concurrent.futures import Future

        future = Future()
        future.set_result((fn(*args), time.time(), 0.0, 0.0))
        future.submitted, future.lane = time.time(), lane
        return future

    def latency(self, future):
        return future.result()[0], 0.0


def test_a_wall_clock_plan_executes_with_the_parameters_it_was_certified_with(setup):
    """Guarantee 6 in wall-clock time: the call for the plan that starts at t_k is submitted at
    t_(k-1) with the estimate of then; when the estimate tightens in between (0.7 s), the plan
    started at 1.5 s still runs with the parameters of its submission at 0 s, and only the one
    submitted at 1.5 s (started at 3.0 s) with the tight box."""
    from pydrake.systems.primitives import TrajectorySource
    from pydrake.trajectories import PiecewisePolynomial
    from safesysid.systems.hardware.background import WallClockPlanner

    robot, planner, (theta0, lo, hi) = setup
    own = SafePlanner(robot, planner.config, obstacles=[], payload=None, tracking=planner.tracking)
    tight = (theta0, theta0 - 0.5 * (theta0 - lo), theta0 + 0.5 * (hi - theta0))
    sources = [
        TrajectorySource(PiecewisePolynomial.ZeroOrderHold([0.0, 0.7, 10.0], np.stack([a, b, b], 1)))
        for a, b in zip((theta0, lo, hi), tight)
    ]
    system = WallClockPlanner(own, Q0, theta0, lo, hi, num_plans=3, worker=InProcessWorker())
    st, logs = simulate(system, 3.2, theta_sources=sources)
    assert [r["ok"] for r in st.records] == [True, True, True]
    t = logs[3].sample_times()
    out = np.hstack([log.data().T for log in logs[3:]])
    prior, new = np.concatenate([theta0, lo, hi]), np.concatenate(tight)
    before, after = t <= 3.0, t > 3.0  # a log at t shows the outputs before the updates at t
    assert np.array_equal(out[before], np.broadcast_to(prior, out[before].shape))
    assert np.array_equal(out[after], np.broadcast_to(new, out[after].shape))


def test_an_inconsistent_estimate_is_never_planned_with(setup):
    robot, planner, thetas = setup
    recording = Recording(planner)
    system = ExcitingPlanner(recording, Q0, *thetas)
    st, logs = simulate(system, 2.0, connect_thetas=thetas, consistent=0.0)
    assert recording.calls == [] and st.plan is None and st.done
    assert [e["kind"] for e in st.events] == ["plan_refused"]
    assert np.allclose(logs[0].data().T, Q0) and np.allclose(logs[1].data(), 0)


def test_two_contexts_do_not_share_plans_or_the_random_generator(setup):
    """Every PlanResult and the random generator live in PlannerState: two simulations of ONE
    diagram advanced alternately each draw the same random plans as a simulation alone (with the
    generator on the system object, the second would continue the first's stream)."""
    robot, planner, thetas = setup
    system = ExcitingPlanner(planner, Q0, *thetas, num_plans=3, mode="random", seed=3)
    builder = DiagramBuilder()
    builder.AddSystem(system)
    for k, value in enumerate(thetas):
        builder.Connect(builder.AddSystem(ConstantVectorSource(value)).get_output_port(), system.get_input_port(k))
    diagram = builder.Build()

    def plans(sim):
        results = system.results(system.GetMyContextFromRoot(sim.get_context()))
        assert len(results) == system.planner_state(system.GetMyContextFromRoot(sim.get_context())).calls
        return [r.k.tolist() for r in results]

    stops = (0.1, 1.6, 3.1)
    together = [Simulator(diagram), Simulator(diagram)]
    for stop in stops:
        for sim in together:
            sim.AdvanceTo(stop)
    alone = Simulator(diagram)
    for stop in stops:
        alone.AdvanceTo(stop)
    assert len(plans(alone)) == 3 and all(
        r.ok for r in system.results(system.GetMyContextFromRoot(alone.get_context()))
    )
    assert plans(together[0]) == plans(together[1]) == plans(alone)


def test_cumulative_excitation_hands_each_call_the_executed_motion(setup):
    """planner.cumulative_excitation: before each call the executed part of the running plan
    (from its start to now) is appended to the past rows the exciting cost stacks; off: none."""
    import dataclasses

    robot, planner, thetas = setup
    cumulative = SafePlanner(
        robot,
        dataclasses.replace(planner.config, cumulative_excitation=True),
        obstacles=[],
        payload=None,
        tracking=planner.tracking,
    )
    st, _ = simulate(ExcitingPlanner(cumulative, Q0, *thetas, num_plans=3), 4.6, connect_thetas=thetas)
    assert st.calls == 3 and all(r["ok"] for r in st.records)
    executed = [cumulative.executed_rows(res, 1.5) for res in st.results[:2]]
    np.testing.assert_array_equal(st.past, np.vstack(executed))
    off = SafePlanner(
        robot,
        dataclasses.replace(planner.config, cumulative_excitation=False),
        obstacles=[],
        payload=None,
        tracking=planner.tracking,
    )  # the default is on (planner.cumulative_excitation: true)
    st_off, _ = simulate(ExcitingPlanner(off, Q0, *thetas, num_plans=3), 4.6, connect_thetas=thetas)
    assert st_off.past is None
