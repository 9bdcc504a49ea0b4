"""Every plan is executed with the parameters it was certified with (Algorithm 2's order).

At each t_p the planner certifies the next plan for some (theta0, [theta]); the controller that
executes it must use exactly those, from the plan's first instant to its last, whatever the
estimator publishes meanwhile (a tighter box, or the wider hull it publishes when an update is
inconsistent). A stub estimator changes its box at t_p: it tightens it at 1.5 s, then widens it and
flags the estimate inconsistent at 3.0 s, after which the planner must not plan again.
"""

import numpy as np
import pytest
from pydrake.systems.framework import BasicVector, LeafSystem
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.systems.plant.arm_plant import scenario_dumbbell, true_theta


class StubEstimator(LeafSystem):
    """The estimator's ports; publishes boxes[j] (theta0, lower, upper, consistent) from j t_p on."""

    def __init__(self, robot, boxes, period_s):
        super().__init__()
        n, p = robot.n, 14 * robot.n
        self.robot, self.boxes = robot, boxes
        self.DeclareVectorInputPort("state", 2 * n)
        self.DeclareVectorInputPort("measured_torque", n)
        self._index = self.DeclareDiscreteState(1)
        deps = {self.xd_ticket()}
        for j, name in enumerate(("theta0", "theta_lower", "theta_upper")):
            self.DeclareVectorOutputPort(
                name, p, lambda c, out, j=j: out.SetFromVector(self._box(c)[j]), prerequisites_of_calc=deps
            )
        self.DeclareVectorOutputPort(
            "consistent",
            BasicVector(1),
            lambda c, out: out.SetFromVector([self._box(c)[3]]),
            prerequisites_of_calc=deps,
        )
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, period_s, self._advance)

    def _box(self, context):
        return self.boxes[int(context.get_discrete_state(self._index).get_value()[0])]

    def _advance(self, context, state):
        k = context.get_discrete_state(self._index).get_value()[0]
        state.get_mutable_vector(self._index).SetFromVector([min(k + 1, len(self.boxes) - 1)])

    # what run_online asks of an estimator (about its context)
    def history(self, context):
        return []

    def consistent(self, context):
        return bool(self.boxes[-1][3])

    def events(self, context):
        return []

    def final_estimate(self, context):
        theta0, lo, hi, _ = self.boxes[-1]
        ee = self.robot.ee_slice
        return theta0[ee], lo[ee], hi[ee]


def stub_boxes(robot, scenario, prior):
    """prior until t_p; then a box a quarter as wide around the truth (consistent); then the hull
    of that and the prior widened by half (inconsistent), as the estimator publishes."""
    theta0, box = prior
    truth = true_theta(robot, scenario_dumbbell(scenario))
    ee = robot.ee_slice
    width = box.hi - box.lo
    lo, hi = box.lo.copy(), box.hi.copy()
    lo[ee] = np.maximum(box.lo[ee], truth[ee] - width[ee] / 8)
    hi[ee] = np.minimum(box.hi[ee], truth[ee] + width[ee] / 8)
    tight0 = theta0.copy()
    tight0[ee] = np.clip(truth[ee], lo[ee], hi[ee])
    wide_lo, wide_hi = lo.copy(), hi.copy()
    wide_lo[ee], wide_hi[ee] = box.lo[ee] - width[ee] / 4, box.hi[ee] + width[ee] / 4
    return [(theta0, box.lo, box.hi, 1.0), (tight0, lo, hi, 1.0), (tight0, wide_lo, wide_hi, 0.0)]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """One closed-loop run (4 plans, 7.5 s) with the stub estimator; what the planner was asked to
    certify at each call and what the controller used at each step."""
    from safesysid import online
    from safesysid.systems.controller import systems as controller_systems
    from safesysid.systems.planner import safe_planner as planner

    mp = pytest.MonkeyPatch()
    scenario = load_scenario(SCENARIOS_DIR / "quickstart.yaml")
    calls = []  # per planning call: (theta0, lower, upper, ok)
    plan = planner.SafePlanner.plan

    def recording_plan(self, q, v, a, theta0, lo, hi, **kw):
        res = plan(self, q, v, a, theta0, lo, hi, **kw)
        calls.append((np.array(theta0), np.array(lo), np.array(hi), res.ok))
        return res

    used = []  # (t, theta0 | lower | upper) each time the controller's parameters change
    make = controller_systems.make_controller

    def spying_controller(kind, robot, gains, time_step):
        ctrl = make(kind, robot, gains, time_step=time_step)
        law = ctrl._torque

        def torque(context, *args):
            theta0, box = ctrl._inputs(context)[-2:]  # what the law reads (ARMOUR reads its own inputs)
            params = np.concatenate([theta0, box.lo, box.hi])
            if not used or not np.array_equal(used[-1][1], params) or used[-1][0] > context.get_time():
                used.append((context.get_time(), params))
            return law(context, *args)

        ctrl._torque = torque
        return ctrl

    def stub_estimator(robot, scen, stop_time_s=np.inf, worker=None):  # no task phase here: never stops
        prior = online.prior(robot, scen, "ours")
        return StubEstimator(robot, stub_boxes(robot, scen, prior), scen.planner.replan_period_s)

    mp.setattr(planner.SafePlanner, "plan", recording_plan)
    mp.setattr(controller_systems, "make_controller", spying_controller)
    mp.setattr(online, "make_estimator_system", stub_estimator)
    try:
        summary = online.run_online(scenario, None, method="ours", write=False)
    finally:
        mp.undo()
    return scenario, summary, calls, used


def test_the_controller_uses_the_box_its_plan_was_certified_with_at_every_instant(run):
    scenario, summary, calls, used = run
    period = scenario.planner.replan_period_s
    starts = [j * period for j, call in enumerate(calls) if call[3]]
    certified = [np.concatenate(call[:3]) for call in calls if call[3]]
    assert len(starts) >= 3  # the tightened box (published at 1.5 s) was certified by the plan of 3.0 s
    # The parameters in force at every step: the last change at or before it.
    mismatch = []
    for i, (t, params) in enumerate(used):
        t_next = used[i + 1][0] if i + 1 < len(used) else summary["sim_time_s"]
        j = int(np.searchsorted(starts, t + 1e-9, side="right")) - 1  # the plan executing at t
        if not np.array_equal(params, certified[j]):
            mismatch.append((round(t, 4), round(t_next, 4), j, float(np.max(np.abs(params - certified[j])))))
    print("controller parameters not those of the executing plan (from, to, plan, max diff):", mismatch)
    assert not mismatch


def test_an_inconsistent_estimate_stops_planning_and_the_robot_brakes_on_its_verified_plan(run):
    scenario, summary, calls, used = run
    period = scenario.planner.replan_period_s
    events = summary["events"]
    print(events)
    assert len(calls) == 3  # 0, 1.5, 3.0 s; at 4.5 s the estimate is inconsistent: no planning call
    refused = [e for e in events if e["kind"] == "plan_refused"]
    assert len(refused) == 1 and refused[0]["t"] == pytest.approx(3 * period)
    assert any(e["kind"] == "brake" and e["t"] == pytest.approx(3 * period) for e in events)
    assert [e["t"] for e in events] == sorted(e["t"] for e in events)
    assert summary["planner"]["brakes"] == 1
    assert summary["collisions"] == 0 and summary["max_commanded_torque_ratio"] <= 1.0
    assert summary["max_tracking_error_ratio"] <= 1.0
