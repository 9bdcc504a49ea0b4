"""The fast controller path (systems/controller/armour_fast.py) gives the reference law's results (armour.py)
to 1e-12 on fixed states, including the edges (|r| = 0, wrap at +-pi, zero-width box, invalid
theta inputs), as a LeafSystem too; and the scaling benchmarks run at CI size."""

import json

import numpy as np
import pytest
from safesysid.systems.controller import armour as C
from safesysid.systems.controller.armour_fast import FastArmourLaw, FastControllerDynamics
from safesysid.systems.math.intervals import Interval
from safesysid.systems.model import uncertainty
from safesysid.systems.model.robot_model import load_robot

TOL = 1e-12  # relative to 1 + |x|
FIELDS = ("u", "tau_nom", "v", "w_bar", "V_bar", "h", "lam")


@pytest.fixture(scope="module")
def gains(robot):
    return C.ArmourGains(np.array([5.0] * 4 + [7.0] * 3), 20.0, 0.02)


def _close(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b) / (1 + np.abs(a))))


def _states(n):
    """Fixed states (seeded), plus the edges: r = 0 exactly, errors at +-pi on continuous joints."""
    rng = np.random.default_rng(7)
    states = [tuple(x) for x in rng.normal(size=(20, 5, n)) * np.array([2.0, 1.0, 2.0, 1.0, 3.0])[:, None]]
    q = rng.normal(size=n)
    states.append((q, np.zeros(n), q, np.zeros(n), np.zeros(n)))  # at rest on the path: r = 0
    states.append((q, np.ones(n), q + np.pi, np.ones(n), np.zeros(n)))  # wrap edge
    states.append((q, np.ones(n), q - np.pi + 1e-12, np.ones(n), np.zeros(n)))
    return states


def _boxes(robot):
    theta0, box = uncertainty.parameter_box(
        robot, robot.theta_e, robot.theta_e - 0.3, robot.theta_e + 0.3, rest_ratio=0.05, friction_ratio=0.05
    )
    yield theta0, box
    yield theta0, Interval(theta0, theta0)  # zero width: w_bar = 0 up to rounding
    # Adversarial: theta0 on the box's edge (the estimator's theta0 need not be the centre).
    yield box.hi.copy(), box


def test_fast_regressors_equal_reference(robot):
    ref, fast = C.ControllerDynamics(robot), FastControllerDynamics(robot)
    for q, v, va, aa, x in _states(robot.n):
        for a, b in zip(ref.regressors(q, v, va, aa=aa, x=x), fast.regressors(q, v, va, aa=aa, x=x)):
            assert _close(a, b) <= TOL
        wp, wm = ref.regressors(q, v, va, aa=aa, x=x)
        assert _close(np.vstack([wp, x @ wm]), fast.passivity_and_energy(q, v, va, aa=aa, r=x)) <= TOL
    # A tree that is not a chain takes the general path: the same numbers.
    fast.serial = False
    assert _close(ref.regressors(q, v, va, aa=aa, x=x)[0], fast.regressors(q, v, va, aa=aa, x=x)[0]) <= TOL


def test_fast_law_equals_reference_law(robot, gains):
    ref = C.ControllerDynamics(robot)
    law = FastArmourLaw(FastControllerDynamics(robot), gains)
    worst = 0.0
    for theta0, box in _boxes(robot):
        for state in _states(robot.n):
            a = C.armour_control(ref, gains, *state, theta0, box)
            b = law(*state, theta0, box.lo, box.hi)
            worst = max(worst, *(_close(getattr(a, f), getattr(b, f)) for f in FIELDS))
            assert _close(a.err.r, b.err.r) == 0.0
    assert worst <= TOL, worst
    # A tree that is not a chain takes the reference law: the same numbers.
    law.dyn.serial = False
    b = law(*state, theta0, box.lo, box.hi)
    assert _close(C.armour_control(ref, gains, *state, theta0, box).u, b.u) <= TOL


def test_fast_law_cache_follows_its_inputs(robot, gains):
    """A new box or theta0 (the estimator's update) is used at once; invalid inputs give None."""
    law = FastArmourLaw(FastControllerDynamics(robot), gains)
    ref = C.ControllerDynamics(robot)
    state = _states(robot.n)[0]
    boxes = list(_boxes(robot))
    for theta0, box in boxes + boxes[::-1]:
        b = law(*state, theta0, box.lo, box.hi)
        assert _close(C.armour_control(ref, gains, *state, theta0, box).u, b.u) <= TOL
    theta0, box = boxes[0]
    bad = theta0.copy()
    bad[3] = np.nan
    assert law(*state, bad, box.lo, box.hi) is None
    assert law(*state, theta0, box.hi, box.lo) is None  # lower above upper
    assert law(*state, theta0, box.lo, box.hi) is not None


def test_controller_system_matches_reference_system(robot, gains):
    """The ArmourController LeafSystem (fast path) and the reference one, same fixed inputs:
    torque and diagnostics outputs equal to 1e-12."""
    from safesysid.benchmarks.bench_sim import ReferenceArmourController
    from safesysid.systems.controller import systems as cs

    g = cs.ControllerGains(gains, *(np.ones(robot.n),) * 4, np.ones(10), 0.1)
    systems = [cs.ArmourController(robot, g), ReferenceArmourController(robot, g)]
    contexts = [s.CreateDefaultContext() for s in systems]
    for theta0, box in _boxes(robot):
        for q, v, q_d, qd_d, qdd_d in _states(robot.n)[:6]:
            outs = []
            for system, ctx in zip(systems, contexts):
                for name, value in (
                    ("desired", np.concatenate([q_d, qd_d, qdd_d])),
                    ("state", np.concatenate([q, v])),
                    ("theta0", theta0),
                    ("theta_lower", box.lo),
                    ("theta_upper", box.hi),
                ):
                    system.GetInputPort(name).FixValue(ctx, value)
                outs.append([system.GetOutputPort(p).Eval(ctx) for p in ("torque", "diagnostics")])
            assert max(_close(a, b) for a, b in zip(*outs)) <= TOL


def test_sim_bench_quick_measures_both_paths(tmp_path):
    """bench_sim at CI size: the plant alone and both controller paths in one run, the plot written."""
    from safesysid.benchmarks import bench_sim

    out = bench_sim.run(quick=True, out=tmp_path)
    for key in ("plant_alone_cpu_real_time_factor", "armour_cpu_real_time_factor", "armour_law_cpu_us_per_step"):
        assert out[key] > 0
    assert out["armour_law_fast_vs_reference_max_rel_diff"] <= TOL
    assert (tmp_path / "sim_real_time_factor.png").stat().st_size > 0
    json.dumps(out)


def test_scaling_benchmarks_quick_and_readme_tables(tmp_path):
    """Estimator and regressor scalings at CI size write their plots, and the README tables list
    every size measured; a bench.json from before the scaling fields gives no table, no error."""
    from safesysid.benchmarks import bench_estimator, bench_regressors, readme_table

    results = {
        "estimator": {"scaling": bench_estimator.scaling(quick=True, out=tmp_path)},
        "regressors": {"scaling": bench_regressors.scaling(quick=True, out=tmp_path)},
    }
    for png in ("estimator_vs_length.png", "regressors_vs_batch.png"):
        assert (tmp_path / png).stat().st_size > 0
    rows = results["estimator"]["scaling"]["vs_length_s"]
    assert [r["samples"] for r in rows.values()] == [1500, 7500]
    text = readme_table.tables(json.loads(json.dumps(results, default=float)))
    for needle in ("| 1.5 | 1500 |", "| 7.5 | 7500 |", "| 1 |", "| 100 |", "Pinocchio"):
        assert needle in text
    assert readme_table.tables({"estimator": {"full_update_s": 0.1}, "sim": {"error": "x"}}) == ""
    path = tmp_path / "bench.json"
    path.write_text(json.dumps(results, default=float))
    assert readme_table.main([str(path)]) == 0
    assert readme_table.main([str(tmp_path / "missing.json")]) == 2


def test_fast_hull_contains_the_exact_one(robot, gains):
    """Soundness of the fast path's rounding, checked in exact rational arithmetic: with a
    zero-width box (the hull is a point, only the rounding allowance covers the float error) and
    theta0 = the box, w_bar_i >= |exact Wp_i theta - tau_nom_i| and 2 V_bar >= exact r^T Wm theta r."""
    from fractions import Fraction

    fast = FastControllerDynamics(robot)
    law = FastArmourLaw(fast, gains)
    theta0 = robot.theta * (1 + 1e3 * np.finfo(float).eps)  # not a round number
    exact_theta = [Fraction(x) for x in theta0]
    for q, v, q_d, qd_d, qdd_d in _states(robot.n)[:8]:
        out = law(q, v, q_d, qd_d, qdd_d, theta0, theta0, theta0)
        e = out.err
        a = fast.passivity_and_energy(q, v, e.qd_a, aa=e.qdd_a, r=e.r)
        exact = [sum(Fraction(x) * t for x, t in zip(row, exact_theta)) for row in a]
        for i in range(robot.n):
            assert Fraction(out.w_bar[i]) >= abs(exact[i] - Fraction(out.tau_nom[i]))
        assert Fraction(2 * out.V_bar) >= exact[robot.n]


def test_replayed_law_gives_the_plant_the_same_torques_without_computing_the_law(monkeypatch):
    """bench_sim's per-step breakdown: inside _replayed_law a second run of the same loop commands
    the same torques bit for bit while the fast law is never called: what remains is the loop
    around the law (freezing the law's first output instead changed the plant's work)."""
    from safesysid.benchmarks import bench_sim
    from safesysid.closed_loop import build_closed_loop, simulate_closed_loop
    from safesysid.scenario import load_scenario
    from safesysid.systems.model.loading import robot_from_scenario

    s = load_scenario(overrides={"payload": {"dumbbell": "8lb"}})
    robot = robot_from_scenario(s)
    theta0, box = uncertainty.parameter_box(
        robot, s.initial_interval.nominal, s.initial_interval.lower, s.initial_interval.upper
    )
    q0, trajectory = bench_sim._trajectory(s, robot)
    calls = []
    call = FastArmourLaw.__call__
    monkeypatch.setattr(FastArmourLaw, "__call__", lambda self, *inputs: calls.append(1) or call(self, *inputs))

    def torques():
        loop = build_closed_loop(s, trajectory, theta0, theta_box=box, kind="armour", robot=robot)
        return simulate_closed_loop(loop, q0, 0.2)["torque"]

    with bench_sim._replayed_law():
        live = torques()
        computed = len(calls)
        replayed = torques()
    assert computed >= 200 and len(calls) == computed
    np.testing.assert_array_equal(live[1], replayed[1])


def test_grasp_load_of_a_steady_rotation_about_the_base(tmp_path):
    """experiments/grasp_load.py: joint 1 turning at a constant w, the other joints still, so the grasp
    point circles the base axis: the dumbbell needs m sqrt(g^2 + (w^2 r)^2), r its distance from the
    axis; no angular acceleration."""
    from grasp_load import grasp_load

    robot = load_robot()
    q0 = np.array([0.0, 0.4, 0.0, 1.2, 0.0, 0.6, 0.0])
    w, t = 0.8, np.arange(0.0, 0.5, 0.001)
    q = np.tile(q0, (len(t), 1))
    q[:, 0] = w * t
    v = np.zeros_like(q)
    v[:, 0] = w
    columns = ["t"] + [f"{x}{i}" for x in ("q", "v", "tau") for i in range(1, 8)]
    log = np.column_stack([t, q, v, np.zeros_like(q)])
    np.savetxt(tmp_path / "log.csv", log, delimiter=",", header=",".join(columns), comments="")
    theta_e = robot.theta[robot.ee_slice].copy()
    theta_e[0] += 3.63
    (tmp_path / "summary.json").write_text(json.dumps({"method": "test", "payload_true": {"theta": theta_e.tolist()}}))
    fk = robot.forward_kinematics(q0[None])
    R, p = fk.R[0, robot.end_effector], fk.p[0, robot.end_effector]
    r = np.hypot(*(R @ robot.extra["grasp_point"] + p)[:2])
    load = grasp_load(tmp_path)
    assert load["dumbbell_kg"] == pytest.approx(3.63)
    assert load["peak_force_N"] == pytest.approx(3.63 * np.hypot(9.81, w**2 * r), rel=1e-6)
    assert load["peak_angular_acceleration"] < 1e-6


def test_interval_budget_counts_pairs_with_and_without_the_mass(capsys):
    """The closed-loop table counts pairs where ours is narrower on >= 8 of 10 parameters, and
    again were the mass (whose width the motion does not move) won or lost in every pair."""
    from safesysid.benchmarks.interval_budget import print_closed_loop

    ones = np.ones(10)

    def method(ratios):
        n = len(ratios)
        return dict(
            published_ratio=ones,
            data_ratio=ones,
            first_order_ratio=ones,
            data_ratios=ratios,
            published_ratios=ratios,
            contains=[True] * n,
            consistent=[True] * n,
            cond_Y=[1.0] * n,
            mass_half_width_kg=[0.1] * n,
            safety={"success": n},
            solve_time_s=[0.1] * n,
        )

    ours = np.full((3, 10), 0.5)
    ours[:, 0] = 2.0  # the mass lost in every pair
    ours[1, 1:3] = 2.0  # pair 1: 7 of the other 9 won, pair 2: one more lost
    ours[2, 1:4] = 2.0
    print_closed_loop({"ours": method(ours), "random": method(np.ones((3, 10)))})
    out = capsys.readouterr().out
    assert "per pair: [9, 7, 6]; pairs with >= 8: 1" in out
    assert "were m won in every pair: 2, lost: 1" in out
    # the restated target on the published widths: per-parameter medians (m, mcx, mcy lost) and pairs won
    assert "median over pairs: [2.0, 2.0, 2.0, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5] (7/10 < 1)" in out
    assert "fraction of pairs ours narrower: [0.0, 0.33, 0.33, 0.67, 1.0," in out
