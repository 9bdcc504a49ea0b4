"""ExcitingPlanner LeafSystem: receding horizon, continuity across replans, braking on failure."""
import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, VectorLogSink

from safesysid.scenario import Planner
from safesysid.systems import controller as ctl
from safesysid.systems.planner import PlanResult, SafePlanner
from safesysid.systems.planner_system import ExcitingPlanner
from safesysid.systems.robot_model import load_robot

Q0 = np.array([0.0, 0.26, 0.0, 2.0, 0.0, 0.9, 1.57])


@pytest.fixture(scope="module")
def setup():
    robot = load_robot(coulomb_smoothing=0.01)
    theta0 = robot.theta.copy()
    rel = 0.05 * np.abs(theta0)
    lo, hi = theta0 - rel, theta0 + rel
    gains = ctl.ArmourGains(Kr=np.array([5.0] * 4 + [7.0] * 3), alpha=20.0, V_max=0.02)
    planner = SafePlanner(robot, Planner(num_cost_samples=32), [], None, ctl.tracking_bounds_for(robot, gains, lo))
    return robot, planner, (theta0, lo, hi)


def simulate(system, t_end, connect_thetas=None):
    builder = DiagramBuilder()
    builder.AddSystem(system)
    if connect_thetas is not None:
        for k, value in enumerate(connect_thetas):
            src = builder.AddSystem(ConstantVectorSource(value))
            builder.Connect(src.get_output_port(), system.get_input_port(k))
    logs = []
    for k in range(3):
        log = builder.AddSystem(VectorLogSink(7, publish_period=0.005))
        builder.Connect(system.get_output_port(k), log.get_input_port())
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
    q, v, a = (log.data().T for log in logs)
    # Continuity of q, qd (and qdd) across the replans: the next plan starts at the old state.
    dt = np.diff(t)
    assert np.max(np.abs(np.diff(q, axis=0))) < 1.5 * np.max(np.abs(v)) * dt.max() + 1e-9
    assert np.max(np.abs(np.diff(v, axis=0))) < 1.5 * np.max(np.abs(a)) * dt.max() + 1e-9
    # It moves, and the last plan (started at 4.5 s) is at rest from 7.5 s on.
    assert np.max(np.abs(q - Q0)) > 0.02
    late = t >= 7.5
    assert np.allclose(v[late], 0, atol=1e-12) and np.allclose(a[late], 0, atol=1e-12)
    assert np.allclose(q[late], st.plan.q_end)


def test_failed_plan_keeps_the_previous_one_which_brakes(setup):
    robot, planner, thetas = setup

    class FailsSecond:
        """The real planner, except that the second call reports failure (solver failure)."""

        def __init__(self, inner):
            self.inner, self.config, self.robot, self.calls = inner, inner.config, inner.robot, 0

        def plan(self, *args, **kw):
            self.calls += 1
            if self.calls == 2:
                return PlanResult(ok=False, status="solver_failed", reason="test")
            return self.inner.plan(*args, **kw)

    system = ExcitingPlanner(FailsSecond(planner), Q0, *thetas)
    st, logs = simulate(system, 5.0)  # theta ports unconnected: the constructor's values are used
    assert st.calls == 2 and st.done
    assert st.records[1]["braking"] and not st.records[1]["ok"]
    t = logs[0].sample_times()
    v = logs[1].data().T
    assert np.max(np.abs(v[t < 2.9])) > 1e-3  # moving along the first plan ...
    assert np.allclose(v[t >= 3.0], 0, atol=1e-12)  # ... which ends at rest at 3 s
    assert st.t_start == 0.0


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
    assert np.allclose(logs[0].data().T, Q0) and np.allclose(logs[1].data(), 0)
