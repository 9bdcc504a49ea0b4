"""The planner's constraints are conservative in continuous time (checked densely with Drake's
signed distance on the true geometry, the actual ARMOUR law and random parameters), they are not
vacuous, and the exciting cost is right."""

import numpy as np
import pytest
from helpers import mass_matrices, n_trials
from safesysid.benchmarks.bench_planner import parameter_box as theta_box  # one definition of the test prior
from safesysid.systems.config import Obstacle, Planner
from safesysid.systems.controller import armour as ctl
from safesysid.systems.math.intervals import Interval
from safesysid.systems.model import uncertainty
from safesysid.systems.model.payload import load_dumbbells
from safesysid.systems.model.robot_model import MODELS_DIR
from safesysid.systems.model.torque_noise import DeclaredTorqueNoise
from safesysid.systems.planner import reachability as reach
from safesysid.systems.planner import safe_planner as P
from safesysid.systems.planner.ee_regressor import ee_standard_regressor

Q0 = np.array([0.0, 0.26, 0.0, 2.0, 0.0, 0.9, 1.57])
GAINS = ctl.ArmourGains(Kr=np.array([5.0] * 4 + [7.0] * 3), alpha=20.0, V_max=0.02)


@pytest.fixture(scope="module")
def payload():
    return load_dumbbells(MODELS_DIR / "dumbbells.yaml")["4lb"]


def scene_obstacles():
    """Three boxes 6-12 cm from the arm/payload at Q0 (in front, beside, above the wrist)."""
    return [
        Obstacle(name="front", xyz_m=[0.56, -0.02, 0.17], rpy_rad=[0, 0, 0.3], size_m=[0.1, 0.3, 0.34]),
        Obstacle(name="side", xyz_m=[0.30, 0.27, 0.30], rpy_rad=[0, 0, -0.4], size_m=[0.2, 0.08, 0.4]),
        Obstacle(name="above", xyz_m=[0.28, -0.05, 0.88], rpy_rad=[0.2, 0, 0], size_m=[0.3, 0.3, 0.1]),
    ]


def make_planner(robot, payload, obstacles, **cfg):
    theta0, lo, hi = theta_box(robot, payload)
    bounds = ctl.tracking_bounds_for(robot, GAINS, lo)
    config = Planner(**{"num_cost_samples": 32, **cfg})
    return P.SafePlanner(robot, config, obstacles=obstacles, payload=payload, tracking=bounds), (theta0, lo, hi)


def cost_fd_gradient(prob, k, h=1e-6):
    """Central finite differences of the exciting cost in each k_j."""
    cost = lambda x: prob.exciting_cost(x)[0]  # noqa: E731
    return np.array([(cost(k + h * e) - cost(k - h * e)) / (2 * h) for e in np.eye(7)])


class DrakeScene:
    """The true geometry, independent of the planner's spheres: the URDF's link shapes, the
    dumbbell's cylinders at the grasp point (not its covering spheres), the boxes and the floor,
    queried with Drake's signed distance."""

    def __init__(self, robot, payload, obstacles):
        from pydrake.geometry import Box, Cylinder
        from pydrake.math import RigidTransform, RollPitchYaw
        from pydrake.multibody.plant import CoulombFriction
        from pydrake.systems.framework import DiagramBuilder
        from safesysid.systems.model.robot_model import make_plant

        builder = DiagramBuilder()
        self.plant, self.sg, _ = make_plant(robot.source, builder=builder)
        plant = self.plant
        self.obstacle_ids = set()
        for o in obstacles:
            self.obstacle_ids.add(
                plant.RegisterCollisionGeometry(
                    plant.world_body(),
                    RigidTransform(RollPitchYaw(o.rpy_rad), o.xyz_m),
                    Box(*o.size_m),
                    o.name,
                    CoulombFriction(),
                )
            )
        ee = plant.GetBodyByName(robot.body_names[robot.end_effector])
        grasp = np.asarray(robot.extra["grasp_point"], float)
        for k, (_, x, r, length) in enumerate(payload.parts()):
            pose = RigidTransform(RollPitchYaw(0, np.pi / 2, 0), grasp + [x, 0, 0])  # cylinder z -> EE x
            plant.RegisterCollisionGeometry(ee, pose, Cylinder(r, length), f"payload_{k}", CoulombFriction())
        # The floor slab's top face at z = 0 (Planner.floor_z_m); the base standing on it is welded
        # to the world, so SceneGraph never reports that pair.
        self.floor_id = plant.RegisterCollisionGeometry(
            plant.world_body(), RigidTransform([0, 0, -0.05]), Box(4, 4, 0.1), "floor", CoulombFriction()
        )
        plant.Finalize()
        self.diagram = builder.Build()
        self.ctx = self.diagram.CreateDefaultContext()
        self.pctx = plant.GetMyContextFromRoot(self.ctx)
        self.sgctx = self.sg.GetMyContextFromRoot(self.ctx)

    def min_obstacle_distance(self, q):
        return self.distances(q)[0]

    def distances(self, q):
        """(smallest distance of the arm and payload to the boxes, to the floor) at q."""
        self.plant.SetPositions(self.pctx, q)
        query = self.sg.get_query_output_port().Eval(self.sgctx)
        best, floor = np.inf, np.inf
        for pair in query.ComputeSignedDistancePairwiseClosestPoints(0.3):
            if (pair.id_A in self.obstacle_ids) != (pair.id_B in self.obstacle_ids):
                best = min(best, pair.distance)
            elif self.floor_id in (pair.id_A, pair.id_B):
                floor = min(floor, pair.distance)
        return best, floor


def check_plan_densely(robot, planner, thetas, k, scene, rng, samples=400, gains=GAINS):
    """Continuous trajectory at dense instants + random tracking errors inside the ultimate bound +
    random theta in [theta]: no penetration, limits hold, |u| of the ARMOUR law within limits at
    states ON the tube boundary (true V = V_max, so h < 0 mostly)."""
    theta0, lo, hi = thetas
    prob_reach = planner._last_problem.reach
    jp = robot.joint_params
    b = planner.tracking
    n = robot.n
    t = np.sort(np.concatenate([rng.uniform(0, prob_reach.T, samples - 2), [0.0, prob_reach.T]]))
    qd, vd, ad = prob_reach.bezier.evaluate(t, prob_reach.q_end(k))
    dyn = ctl.ControllerDynamics(robot)
    box = Interval(lo, hi)
    stats = dict(samples=0, torque_samples=0, negative_h=0, min_distance=np.inf, max_torque_ratio=0.0)
    # The random draws first, in the order they always had (e, edot, theta_true, direction of r);
    # the true mass matrices then in one batch (helpers.mass_matrices).
    drawn = []
    for _ in range(len(t)):
        e = rng.uniform(-1, 1, n) * b.position
        edot = rng.uniform(-1, 1, n) * b.velocity
        theta_true = rng.uniform(lo, hi)
        if rng.uniform() < 0.5:
            theta_true = np.where(rng.uniform(size=lo.size) < 0.5, lo, hi)
        drawn.append((e, edot, theta_true, rng.normal(size=n)))
    m_true = mass_matrices(robot, qd - np.array([d[0] for d in drawn]), np.array([d[2] for d in drawn]))
    for m, (e, edot, theta_true, direction) in enumerate(drawn):
        q, v = qd[m] - e, vd[m] - edot
        assert np.all(q >= jp.position_lower) and np.all(q <= jp.position_upper)
        assert np.all(np.abs(v) <= jp.velocity_limit)
        dist, floor = scene.distances(q)
        assert dist >= 0.0 and floor >= 0.0, f"penetration {dist} (floor {floor}) at t={t[m]}"
        stats["min_distance"] = min(stats["min_distance"], dist)
        stats["samples"] += 1
        # Torque: the ARMOUR command on the tube boundary: r in a random direction with the TRUE
        # 1/2 r^T M(q; theta_true) r = V_max (theta_true a box vertex half the time), edot = r - Kr e.
        r = direction * np.sqrt(2 * gains.V_max / (direction @ m_true[m] @ direction))
        v = vd[m] - (r - gains.Kr * e)
        out = ctl.armour_control(dyn, gains, q, v, qd[m], vd[m], ad[m], theta0, box)
        assert np.all(np.abs(out.u) <= jp.torque_limit)
        tau_true = dyn.regressors(q, v, out.err.qd_a, aa=out.err.qdd_a, x=out.err.r)[0] @ theta_true
        assert np.all(np.abs(tau_true) <= jp.torque_limit)
        stats["torque_samples"] += 1
        stats["negative_h"] += out.h < 0
        stats["max_torque_ratio"] = max(stats["max_torque_ratio"], float(np.max(np.abs(out.u) / jp.torque_limit)))
    return stats


def keep_last_problem(planner):
    """The planner, keeping its last PlanningProblem as planner._last_problem (check_plan_densely)."""
    orig = planner.problem

    def keep(*args, **kw):
        planner._last_problem = orig(*args, **kw)
        return planner._last_problem

    planner.problem = keep
    return planner


@pytest.fixture(scope="module")
def planned(robot, payload):
    """A planner on the 3-box scene, with its last problem kept for the dense checks."""
    obstacles = scene_obstacles()
    planner, thetas = make_planner(robot, payload, obstacles)
    return keep_last_problem(planner), thetas, DrakeScene(robot, payload, obstacles)


def test_ee_regressor_equals_the_robot_model_columns(robot):
    rng = np.random.default_rng(0)
    q, v, a = (rng.normal(size=(20, robot.n)) for _ in range(3))
    ours = ee_standard_regressor(robot.tree, robot.end_effector, q, v=v, a=a)
    assert np.allclose(ours, robot.standard_regressor(q, v, a)[..., robot.ee_slice], atol=1e-12)


def test_exciting_cost_gradient_matches_finite_differences(robot, payload, planned):
    planner, thetas, _ = planned
    rng = np.random.default_rng(1)
    prob = planner.problem(Q0 + 0.1, rng.uniform(-0.2, 0.2, 7), rng.uniform(-0.2, 0.2, 7), *thetas)
    for _ in range(3):
        k = rng.uniform(-1, 1, 7)
        val, grad, W = prob.exciting_cost(k)
        s = np.linalg.svd(W, compute_uv=False)
        assert np.isclose(val, np.log(s[0] / s[-1]))
        h = 1e-6
        fd = np.array(
            [(prob.exciting_cost(k + h * e)[0] - prob.exciting_cost(k - h * e)[0]) / (2 * h) for e in np.eye(7)]
        )
        assert np.allclose(grad, fd, rtol=1e-5, atol=1e-6)


def test_inertia_columns_cost_is_the_log_cond_of_the_six_inertia_columns(robot, payload):
    """planner.exciting_columns: inertia conditions W_e[:, 4:10] (the rotational inertias): value and
    its exact gradient (what the solver follows)."""
    planner, thetas = make_planner(robot, payload, [], exciting_columns="inertia")
    rng = np.random.default_rng(11)
    prob = planner.problem(Q0 + 0.1, rng.uniform(-0.2, 0.2, 7), rng.uniform(-0.2, 0.2, 7), *thetas)
    k = rng.uniform(-1, 1, 7)
    val, grad, W = prob.exciting_cost(k)
    assert W.shape[1] == 6
    q, v, a = prob.desired_at(prob.t_cost, k)
    full = ee_standard_regressor(robot.tree, robot.end_effector, q, v=v, a=a).reshape(-1, 10)
    assert np.isclose(val, np.log(np.linalg.cond(full[:, 4:10])))
    fd = cost_fd_gradient(prob, k)
    assert np.allclose(grad, fd, rtol=1e-5, atol=1e-6)


def test_cumulative_cost_conditions_the_past_motion_with_the_plan(robot, payload):
    """planner.cumulative_excitation: the cost is log cond([past; W_e(k)]) with the past motion's
    rows (executed_rows of an earlier plan) on top, its gradient exact; a plan that repeats the
    past motion is worth less than alone, so the optimum moves elsewhere."""
    planner, thetas = make_planner(robot, payload, [])
    first = planner.plan(Q0, np.zeros(7), np.zeros(7), *thetas)
    assert first.ok, first.reason
    past = planner.executed_rows(first, planner.config.replan_period_s)
    spacing = planner.config.duration_s / (planner.config.num_cost_samples - 1)
    assert past.shape == (7 * len(np.arange(0.0, planner.config.replan_period_s, spacing)), 10)
    q, v, a = (x[0] for x in first.evaluate([planner.config.replan_period_s]))
    alone, stacked = (planner.problem(q, v, a, *thetas, past=p) for p in (None, past))
    rng = np.random.default_rng(5)
    k = rng.uniform(stacked.k_lo, stacked.k_hi)
    val, grad, W = stacked.exciting_cost(k)
    assert np.isclose(val, np.log(np.linalg.cond(np.vstack([past, W]))))
    assert np.allclose(W, alone.exciting_cost(k)[2])  # the plan's own W_e (its cond is reported)
    fd = cost_fd_gradient(stacked, k)
    assert np.allclose(grad, fd, rtol=1e-5, atol=1e-6)
    # The optimum of the plan alone and of the plan after the past motion differ.
    k_alone = planner.plan(q, v, a, *thetas, k_init=first.k).k
    k_stacked = planner.plan(q, v, a, *thetas, k_init=first.k, past=past).k
    assert np.max(np.abs(k_alone - k_stacked)) > 1e-3


def test_noise_weighted_cost_divides_each_row_by_its_declared_noise_bound(robot, payload):
    """planner.exciting_weighting noise: the cost is log cond of W_e with each row divided by
    ratio |tau| + floor, tau the nominal torque of the plan that keeps k = 0 at that instant; the
    past rows by their own nominal torque; exact gradient; the reported W_e (and cond) stays
    unweighted."""
    planner, thetas = make_planner(robot, payload, [], exciting_weighting="noise")
    planner.declared_noise = DeclaredTorqueNoise(0.025, 0.05)
    rng = np.random.default_rng(12)
    q0, v0, a0 = Q0 + 0.1, rng.uniform(-0.2, 0.2, 7), rng.uniform(-0.2, 0.2, 7)
    first = planner.plan(Q0, np.zeros(7), np.zeros(7), *thetas)
    assert first.ok, first.reason
    past = planner.executed_rows(first, planner.config.replan_period_s, thetas[0])
    prob = planner.problem(q0, v0, a0, *thetas, past=past)
    k = rng.uniform(prob.k_lo, prob.k_hi)
    val, grad, W = prob.exciting_cost(k)

    def weights(q, v, a):
        tau = np.einsum("snp,p->sn", robot.standard_regressor(q, v, a), thetas[0])
        return (1.0 / (0.025 * np.abs(tau) + 0.05)).ravel()

    spacing = planner.config.duration_s / (planner.config.num_cost_samples - 1)
    qp, vp, ap = first.evaluate(np.arange(0.0, planner.config.replan_period_s, spacing))
    past_plain = ee_standard_regressor(robot.tree, robot.end_effector, qp, v=vp, a=ap).reshape(-1, 10)
    assert np.allclose(past, past_plain * weights(qp, vp, ap)[:, None])
    q, v, a = prob.desired_at(prob.t_cost, k)
    plain = ee_standard_regressor(robot.tree, robot.end_effector, q, v=v, a=a).reshape(-1, 10)
    assert np.allclose(W, plain)
    still = prob.desired_at(prob.t_cost, np.clip(np.zeros(7), prob.k_lo, prob.k_hi))
    weighted = np.vstack([past, plain * weights(*still)[:, None]])
    assert np.isclose(val, np.log(np.linalg.cond(weighted)))
    assert not np.isclose(val, np.log(np.linalg.cond(np.vstack([past_plain, plain]))), rtol=1e-3)
    fd = cost_fd_gradient(prob, k)
    assert np.allclose(grad, fd, rtol=1e-5, atol=1e-6)


def checked_criterion_cost(robot, payload, criterion, seed):
    """(value, W_e(k), past, thetas) of an exciting criterion at a random k below 70 random past
    rows, after checking its exact gradient against finite differences."""
    planner, thetas = make_planner(robot, payload, [], exciting_criterion=criterion)
    rng = np.random.default_rng(seed)
    past = rng.normal(size=(70, 10))
    prob = planner.problem(Q0 + 0.1, rng.uniform(-0.2, 0.2, 7), rng.uniform(-0.2, 0.2, 7), *thetas, past=past)
    k = rng.uniform(-1, 1, 7)
    val, grad, W = prob.exciting_cost(k)
    assert np.allclose(grad, cost_fd_gradient(prob, k), rtol=1e-5, atol=1e-6)
    return val, W, past, thetas


def test_a_optimal_cost_is_the_weighted_least_squares_variance(robot, payload):
    """planner.exciting_criterion a_optimal: log sum_j (A^-1)_jj / width_j^2 with A = S^T S of
    [past; W_e(k)] and width the end effector's current interval (floored at 1e-6); exact gradient."""
    val, W, past, thetas = checked_criterion_cost(robot, payload, "a_optimal", 12)
    S = np.vstack([past, W])
    width = np.maximum((thetas[2] - thetas[1])[robot.ee_slice], 1e-6)  # floored: a zero width stays finite
    assert np.isclose(val, np.log(np.sum(np.diag(np.linalg.inv(S.T @ S)) / width**2)))


@pytest.mark.parametrize("criterion", ["e_optimal", "cond_interval"])
def test_interval_scaled_costs(robot, payload, criterion):
    """planner.exciting_criterion e_optimal: -log sigma_min, cond_interval: log cond, of [past; W_e(k)]
    with each column multiplied by its parameter's current interval width; exact gradients."""
    val, W, past, thetas = checked_criterion_cost(robot, payload, criterion, 13)
    width = np.maximum((thetas[2] - thetas[1])[robot.ee_slice], 1e-6)
    s = np.linalg.svd(np.vstack([past, W]) * width, compute_uv=False)
    assert np.isclose(val, -np.log(s[-1]) if criterion == "e_optimal" else np.log(s[0] / s[-1]))


def test_d_optimal_cost_is_the_log_determinant(robot, payload):
    """planner.exciting_criterion d_optimal: -1/2 log det S^T S of S = [past; W_e(k)] (any column
    scale adds a constant to it); exact gradient."""
    val, W, past, _ = checked_criterion_cost(robot, payload, "d_optimal", 14)
    S = np.vstack([past, W])
    assert np.isclose(val, -0.5 * np.linalg.slogdet(S.T @ S)[1])


def test_planned_and_random_plans_are_safe_in_continuous_time(robot, planned):
    """Monte Carlo: feasible k (optimized, then random feasible ones) checked densely."""
    planner, thetas, scene = planned
    rng = np.random.default_rng(2)
    res = planner.plan(Q0, np.zeros(7), np.zeros(7), *thetas)
    assert res.ok, res.reason
    ks = [res.k]
    prob = planner._last_problem
    while len(ks) < n_trials(4, 20):
        k = rng.uniform(prob.k_lo, prob.k_hi)
        if prob.is_feasible(k):
            ks.append(k)
    totals = dict(samples=0, torque_samples=0, negative_h=0, min_distance=np.inf, max_torque_ratio=0.0)
    for k in ks:
        st = check_plan_densely(robot, planner, thetas, k, scene, rng, samples=n_trials(250, 1500))
        for key in ("samples", "torque_samples", "negative_h"):
            totals[key] += st[key]
        totals["min_distance"] = min(totals["min_distance"], st["min_distance"])
        totals["max_torque_ratio"] = max(totals["max_torque_ratio"], st["max_torque_ratio"])
    print("conservativeness", len(ks), "plans", totals)
    assert totals["torque_samples"] == totals["samples"] and totals["negative_h"] > 0.3 * totals["samples"]
    # The optimized plan uses the room it has: some obstacle comes within a few cm.
    assert totals["min_distance"] < 0.08


def test_receding_horizon_plans_from_a_moving_state_are_safe(robot, planned):
    planner, thetas, scene = planned
    rng = np.random.default_rng(3)
    res = planner.plan(Q0, np.zeros(7), np.zeros(7), *thetas)
    q, v, a = (x[0] for x in res.evaluate([1.5]))
    for solver in ("ipopt", "snopt"):
        planner.config.solver = solver
        nxt = planner.plan(q, v, a, *thetas, k_init=res.k)
        assert nxt.ok, nxt.reason
        # the new plan starts exactly where the old one is at t_p
        q1, v1, a1 = (x[0] for x in nxt.evaluate([0.0]))
        assert np.allclose(q1, q) and np.allclose(v1, v) and np.allclose(a1, a)
        check_plan_densely(robot, planner, thetas, nxt.k, scene, rng, samples=n_trials(150, 1000))
    planner.config.solver = "ipopt"


def test_a_colliding_plan_is_rejected_and_the_planner_goes_around(robot, payload):
    """Put a box where the payload ends up for k = k_bad: k_bad must be infeasible (the nominal
    trajectory really collides), and the planner must still find a safe plan."""
    n = robot.n
    theta0, lo, hi = theta_box(robot, payload)
    from pydrake.math import RollPitchYaw, RotationMatrix

    # Wider shoulder/elbow ranges than the default so a sphere moves farther than its start margin.
    k_range = [np.pi / 8] * 4 + [np.pi / 20] * 3
    planner, thetas = make_planner(robot, payload, [], k_range_rad=k_range)
    prob = planner.problem(Q0, np.zeros(n), np.zeros(n), theta0, lo, hi)
    sp = planner.spheres
    margin = sp.radius + prob.spread[:4].max(0)
    c0, _ = reach.sphere_centres(robot.tree, sp, Q0[None], with_jacobian=False)
    best = -np.inf
    for pattern in np.sign(np.random.default_rng(5).normal(size=(64, n))):
        k = np.clip(pattern, prob.k_lo, prob.k_hi)
        c, _ = reach.sphere_centres(robot.tree, sp, prob.reach.q_end(k)[None], with_jacobian=False)
        room = np.linalg.norm(c - c0, axis=-1)[0] - margin
        if room.max() > best:
            best, k_bad, s, c1 = room.max(), k, int(room.argmax()), c
    assert best > 0.02
    q_end = prob.reach.q_end(k_bad)
    u = (c1 - c0)[0, s] / np.linalg.norm((c1 - c0)[0, s])
    gap = margin[s] + 0.005
    # A 10 cm cube facing the motion, just outside the start's safety margin.
    gap = sp.radius[s] + prob.spread[:4, s].max() + 0.005
    basis = np.linalg.qr(np.stack([u, np.cross(u, [0, 0, 1.0]), [0, 0, 1.0]], 1))[0]
    basis *= np.sign(np.diag(basis))
    basis[:, 2] = np.cross(basis[:, 0], basis[:, 1])
    rpy = RollPitchYaw(RotationMatrix(basis)).vector()
    need = sp.radius + prob.spread[:4].max(0) + 0.005  # every sphere's start margin
    m = len(sp)
    for dist in np.arange(gap, gap + 0.2, 0.002):  # the nearest placement clear of every sphere
        centre = c0[0, s] + (dist + 0.05) * u
        sd, _ = reach.box_signed_distance(
            c0[0], np.broadcast_to(centre, (m, 3)), np.broadcast_to(basis, (m, 3, 3)), np.full((m, 3), 0.05)
        )
        if np.all(sd >= need):
            break
    box = Obstacle(name="trap", xyz_m=centre.tolist(), rpy_rad=list(rpy), size_m=[0.1, 0.1, 0.1])
    planner, thetas = make_planner(robot, payload, [box], cost="exciting", k_range_rad=k_range, max_solve_time_s=10.0)
    prob = planner.problem(Q0, np.zeros(n), np.zeros(n), theta0, lo, hi)
    scene = DrakeScene(robot, payload, [box])
    assert scene.min_obstacle_distance(q_end) < -0.01  # the nominal end pose really penetrates
    assert prob.feasible_start, prob.reason
    assert not prob.is_feasible(k_bad)
    vals, _ = prob.collision(k_bad, with_jacobian=False)
    assert vals.min() < 0
    # Every sampled k whose nominal trajectory touches the box is rejected.
    rng = np.random.default_rng(6)
    t = np.linspace(0, 3.0, 120)
    colliding = 0
    for _ in range(40):
        k = rng.uniform(prob.k_lo, prob.k_hi)
        q, _, _ = prob.reach.bezier.evaluate(t, prob.reach.q_end(k))
        if min(scene.min_obstacle_distance(x) for x in q) < 0:
            colliding += 1
            assert not prob.is_feasible(k)
    assert colliding > 0
    res = planner.plan(Q0, np.zeros(n), np.zeros(n), theta0, lo, hi, k_init=k_bad)
    assert res.ok, res.reason
    q, _, _ = res.evaluate(np.linspace(0, 3.0, 300))
    assert min(scene.min_obstacle_distance(x) for x in q) > 0


def test_start_inside_an_obstacle_margin_gives_no_plan_and_a_reason(robot, payload):
    n = robot.n
    theta0, lo, hi = theta_box(robot, payload)
    planner, _ = make_planner(robot, payload, [])
    c, _ = reach.sphere_centres(robot.tree, planner.spheres, Q0[None], with_jacobian=False)
    box = Obstacle(name="touching", xyz_m=(c[0, 5] + [0.0, 0.0, 0.0]).tolist(), size_m=[0.05, 0.05, 0.05])
    planner, _ = make_planner(robot, payload, [box])
    res = planner.plan(Q0, np.zeros(n), np.zeros(n), theta0, lo, hi)
    assert not res.ok and res.status == "infeasible_start"
    assert "touching" in res.reason and res.k is None


def test_torque_limits_that_cannot_be_guaranteed_give_no_plan(robot, payload):
    from dataclasses import replace

    weak = replace(robot, joint_params=replace(robot.joint_params, torque_limit=np.full(robot.n, 15.0)))
    theta0, lo, hi = theta_box(robot, payload)
    planner, _ = make_planner(weak, payload, [])
    res = planner.plan(Q0, np.zeros(7), np.zeros(7), theta0, lo, hi)
    assert not res.ok and "torque" in res.reason


def test_exciting_beats_random_on_the_condition_number(robot, payload):
    planner, thetas = make_planner(robot, payload, scene_obstacles(), num_cost_samples=64)
    rng = np.random.default_rng(4)
    res = planner.plan(Q0, np.zeros(7), np.zeros(7), *thetas)
    assert res.ok
    conds = []
    for _ in range(8):
        r = planner.plan(Q0, np.zeros(7), np.zeros(7), *thetas, mode="random", rng=rng)
        assert r.ok and r.status == "random"
        conds.append(r.cond)
    print("cond exciting", res.cond, "random", np.round(conds))
    assert res.cond < 0.8 * np.median(conds)


def test_goal_mode_moves_toward_the_goal(robot, payload):
    planner, thetas = make_planner(robot, payload, [], cost="goal")
    prob = planner.problem(Q0, np.zeros(7), np.zeros(7), *thetas)
    pattern = np.array([0.8, -0.6, 0.4, 0.8, -0.8, 0.8, 0.5])
    goal = prob.reach.q_end(np.where(pattern > 0, pattern * prob.k_hi, -pattern * prob.k_lo))  # inside the allowed box
    planner.config.goal_q_rad = goal.tolist()
    res = planner.plan(Q0, np.zeros(7), np.zeros(7), *thetas)
    assert res.ok and np.linalg.norm(res.q_end - goal) < 0.01
    assert np.linalg.norm(goal - Q0) > 0.05  # a real move


def test_swept_spheres_of_a_plan_contain_the_spheres_along_the_tube(robot, payload):
    planner, thetas = make_planner(robot, payload, [])
    res = planner.plan(Q0, np.zeros(7), np.zeros(7), *thetas)
    assert res.ok
    edges, centres, radii = (res.details[k] for k in ("interval_edges_s", "sphere_centres", "sphere_radii"))
    rng = np.random.default_rng(7)
    t = rng.uniform(0, edges[-1], 2000)
    idx = np.minimum(np.searchsorted(edges, t, side="right") - 1, len(edges) - 2)
    q, _, _ = res.evaluate(t)
    q = q + rng.uniform(-1, 1, q.shape) * planner.tracking.position
    c, _ = reach.sphere_centres(robot.tree, planner.spheres, q, with_jacobian=False)
    gap = np.linalg.norm(c - centres[idx], axis=-1) + planner.spheres.radius - radii[idx]
    assert np.all(gap <= 0)


def test_wall_time_cap_stops_the_solver_and_keeps_a_verified_point(robot, payload):
    for solver in ("ipopt", "snopt"):
        planner, thetas = make_planner(
            robot, payload, scene_obstacles(), solver=solver, max_solve_time_s=0.0, budget="wall_time"
        )
        res = planner.plan(Q0, np.zeros(7), np.zeros(7), *thetas)
        assert res.solver_status == "wall_time_cap"
        assert res.ok and res.status == "best_feasible"  # the warm start, verified feasible
        assert planner.problem(Q0, np.zeros(7), np.zeros(7), *thetas).is_feasible(res.k)


def _table_ii_planner(robot, payload, obstacles, **cfg):
    """A planner with the paper's Table II end-effector interval and the scenario's V_max."""
    from safesysid.scenario import load_scenario

    ii = load_scenario().initial_interval  # the Gen3's declared prior: Table II
    theta0, box = uncertainty.parameter_box(robot, np.array(ii.nominal), np.array(ii.lower), np.array(ii.upper))
    gains = ctl.ArmourGains(GAINS.Kr, GAINS.alpha, load_scenario().controller.V_max)
    config = Planner(**{"num_cost_samples": 32, **cfg})
    planner = P.SafePlanner(
        robot, config, obstacles=obstacles, payload=payload, tracking=ctl.tracking_bounds_for(robot, gains, box.lo)
    )
    return keep_last_problem(planner), (theta0, box.lo, box.hi), gains


def test_table_ii_prior_plans_with_a_shrunk_torque_box_and_stays_within_limits(robot, payload):
    """With the paper's wide Table II end-effector interval and the scenario's V_max (the hardware 0.02,
    certified through the affine tube enclosure) the torque bound rejects the full k box; a shrunk box
    is admitted, and the ARMOUR command stays within limits on the tube boundary."""
    planner, thetas, gains = _table_ii_planner(robot, payload, [])
    res = planner.plan(Q0, np.zeros(7), np.zeros(7), *thetas)
    assert res.ok, res.reason
    assert np.all(res.k_box[1] < 1.0)  # the box had to shrink
    st = check_plan_densely(
        robot,
        planner,
        thetas,
        res.k,
        DrakeScene(robot, payload, []),
        np.random.default_rng(8),
        samples=n_trials(150, 1500),
        gains=gains,
    )
    assert st["negative_h"] > 0.3 * st["samples"]


def test_point_refinement_moves_farther_than_the_certified_box_and_stays_safe(robot, payload):
    """planner.point_refinement: the box certified for every k shrinks to 1/8 of k_range with the
    Table II prior; the refined plan leaves that box (a larger motion), is certified on its own
    point, and passes the dense continuous-time check on the true geometry with the ARMOUR law on
    the tube boundary and random parameters in the box."""
    obstacles = scene_obstacles()
    kw = dict(k_range_rad=[np.pi / 8] * 7)
    boxed, thetas, gains = _table_ii_planner(robot, payload, obstacles, **kw)
    planner, _, _ = _table_ii_planner(robot, payload, obstacles, point_refinement=True, **kw)
    z = np.zeros(7)
    plain = boxed.plan(Q0, z, z, *thetas)
    res = planner.plan(Q0, z, z, *thetas)
    assert plain.ok and res.ok and res.details["refined"], res.reason
    box_half = 0.5 * (plain.k_box[1] - plain.k_box[0])
    assert np.max(np.abs(res.k)) > 1.5 * np.max(box_half)  # outside the box the solver was confined to
    assert np.array_equal(res.k_box[0], res.k) and res.max_torque_ratio <= 1.0
    assert res.cost < plain.cost
    moved = np.abs(res.q_end - Q0).max()
    assert moved > 1.5 * np.abs(plain.q_end - Q0).max()
    # Its reported clearance is that of its own swept spheres to every obstacle and the floor (a
    # point problem keeps only the pairs within 1 mm of their margin: it once reported inf).
    centres, radii = res.details["sphere_centres"], res.details["sphere_radii"]  # (intervals, spheres)
    b, m = planner.boxes, centres.shape[1]
    per_box = [
        reach.box_signed_distance(
            centres.reshape(-1, 3),
            *(np.broadcast_to(x[o], (centres.size // 3,) + x[o].shape) for x in (b.centre, b.rotation, b.half_size)),
        )[0].reshape(-1, m)
        - radii
        for o in range(len(b))
    ]
    floor = (centres[..., 2] - radii - planner.floor_z)[:, ~planner.floor_exempt]
    least = min(floor.min(), *(d.min() for d in per_box))
    assert 0.0 <= res.min_clearance_m < np.inf and res.min_clearance_m == pytest.approx(least, abs=1e-9)
    st = check_plan_densely(
        robot,
        planner,
        thetas,
        res.k,
        DrakeScene(robot, payload, obstacles),
        np.random.default_rng(3),
        samples=n_trials(150, 1500),
        gains=gains,
    )
    assert st["negative_h"] > 0.3 * st["samples"]


def test_refinement_scale_confines_the_wide_solve_and_the_plan_to_that_part_of_the_limit_box(robot, payload):
    """planner.refinement_scale s: the wide solve searches the limit box shrunk by s toward k = 0, so the
    adopted point (on the segment from k = 0 to that optimum) lies in it, and is certified as ever."""
    z = np.zeros(7)
    kw = dict(k_range_rad=[np.pi / 8] * 7, point_refinement=True)
    planner, thetas, _ = _table_ii_planner(robot, payload, scene_obstacles(), refinement_scale=0.3, **kw)
    full = planner.problem(Q0, z, z, *thetas, certify_torque=False)
    base = np.clip(z, full.k_lo, full.k_hi)
    scaled = planner.problem(Q0, z, z, *thetas, certify_torque=False, box_scale=0.3)
    assert np.allclose(scaled.k_lo - base, 0.3 * (full.k_lo - base))
    assert np.allclose(scaled.k_hi - base, 0.3 * (full.k_hi - base))
    res = planner.plan(Q0, z, z, *thetas)
    assert res.ok and res.details["refined"] and res.max_torque_ratio <= 1.0, res.reason
    assert np.all(res.k >= scaled.k_lo - 1e-12) and np.all(res.k <= scaled.k_hi + 1e-12)
    assert np.abs(res.k - base).max() > 0.05 * np.abs(full.k_hi - full.k_lo).max()  # it moves


def test_point_refinement_adopts_only_certified_points(robot, payload, monkeypatch):
    """If no point toward the wider optimum is certified, the plan stays the box's (k_range pi/8),
    or there is no plan when no box fits either (pi/4): a point the certificate rejects is never
    adopted."""
    z = np.zeros(7)
    for k_range, box_fits in ((np.pi / 8, True), (np.pi / 4, False)):
        kw = dict(k_range_rad=[k_range] * 7, point_refinement=True)
        planner, thetas, _ = _table_ii_planner(robot, payload, scene_obstacles(), **kw)
        orig = planner.problem

        def reject_points(*args, orig=orig, **kw):
            prob = orig(*args, **kw)
            if "k_box" in kw:
                prob._fail("rejected by the test")
            return prob

        monkeypatch.setattr(planner, "problem", reject_points)
        res = planner.plan(Q0, z, z, *thetas)
        assert res.ok == box_fits and not res.details["refined"], res.reason
        if box_fits:
            assert np.all(res.k >= res.k_box[0]) and np.all(res.k <= res.k_box[1])
            assert np.any(res.k_box[1] > res.k_box[0])
        else:
            assert "torque limit" in res.reason


def test_a_point_problem_certifies_that_point_only(robot, payload):
    """PlanningProblem on k_box = (k, k): the box is the point, its torque bound is the point's (no
    shrinking), and a point far outside the certifiable motion is refused with the torque reason."""
    planner, thetas, _ = _table_ii_planner(robot, payload, [], k_range_rad=[np.pi / 2] * 7)
    z = np.zeros(7)
    small = np.full(7, 0.05)
    prob = planner.problem(Q0, z, z, *thetas, k_box=(small, small))
    assert prob.feasible_start and np.array_equal(prob.k_lo, small) and np.array_equal(prob.k_hi, small)
    assert prob.torque_ratio <= 1.0
    big = np.array([1.0, 1.0, 1.0, -1.0, 1.0, -1.0, 1.0])  # inside the position and velocity limits
    prob = planner.problem(Q0, z, z, *thetas, k_box=(big, big))
    assert not prob.feasible_start and prob.torque_infeasible and "torque limit" in prob.reason


def test_point_refinement_with_no_admissible_k_gives_no_plan_and_the_reason(robot, payload):
    """A start the position/velocity limits rule out for every k (joint 2 already beyond its
    velocity limit): no plan and the limit's reason, with point_refinement as without it."""
    v0 = np.zeros(7)
    v0[1] = 1.5
    for refine in (False, True):
        planner, thetas = make_planner(robot, payload, [], point_refinement=refine)
        res = planner.plan(Q0, v0, np.zeros(7), *thetas)
        assert not res.ok and res.status == "infeasible_start" and "velocity" in res.reason, res.reason


def test_point_certificate_keeps_a_fast_refined_plan_within_the_torque_limits(robot, payload, monkeypatch):
    """0.75 s plans with the Table II prior: no k box fits the torque limits, so only a point
    certificate gives a plan. The optimum solved without the torque check breaks the limits on the tube
    boundary (the dense check fails on it: adopting it uncertified would be unsafe); the point
    the certificate adopts passes the same check."""
    obstacles = scene_obstacles()
    kw = dict(point_refinement=True, k_range_rad=[np.pi / 4] * 7, duration_s=0.75, replan_period_s=0.375)
    planner, thetas, gains = _table_ii_planner(robot, payload, obstacles, **kw)
    targets = []
    optimize = planner._optimize

    def record(prob, *args):
        out = optimize(prob, *args)
        targets.append(out[0])
        return out

    monkeypatch.setattr(planner, "_optimize", record)
    z = np.zeros(7)
    boxed, _, _ = _table_ii_planner(robot, payload, obstacles, **{**kw, "point_refinement": False})
    no_box = boxed.plan(Q0, z, z, *thetas)
    assert not no_box.ok and "torque limit" in no_box.reason  # no k box fits
    res = planner.plan(Q0, z, z, *thetas)
    assert res.ok and res.details["refined"], res.reason
    scene = DrakeScene(robot, payload, obstacles)
    with pytest.raises(AssertionError):
        check_plan_densely(robot, planner, thetas, targets[-1], scene, np.random.default_rng(3), 150, gains)
    assert np.max(np.abs(res.k)) < np.max(np.abs(targets[-1]))
    check_plan_densely(robot, planner, thetas, res.k, scene, np.random.default_rng(3), n_trials(150, 1500), gains)


@pytest.mark.parametrize(
    "target, violated",
    [
        ([0.0, 1.0, 0.0, 1.0, 0.0, -1.0, 0.0], "floor"),  # the payload reaches 2.9 cm into the floor
        ([1.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], "limit"),  # joint 1 beyond its position/velocity limit box
    ],
)
def test_point_refinement_never_adopts_a_target_that_collides_or_leaves_a_limit(robot, payload, target, violated):
    """Guarantees 2/4 on the refined point: the wide solve (uncertified, here made to answer a target
    that reaches into the floor, or one outside the limit box) is only a direction; the adopted point
    passes the collision and limit checks of any plan, or the certified box's plan is used. Judged on
    the true geometry (Drake signed distance on the link shapes and the payload's cylinders)."""
    planner, thetas = make_planner(robot, payload, [], point_refinement=True, k_range_rad=[np.pi / 6] * 7)
    optimize, answers = planner._optimize, []

    def wide_answers_target(prob, *args):
        if np.isnan(prob.torque_ratio):  # the wide solve (no torque certificate) of _refine
            answers.append(np.asarray(target, float))
            return answers[-1], "solved", "test target"
        return optimize(prob, *args)

    planner._optimize = wide_answers_target
    z = np.zeros(7)
    res = planner.plan(Q0, z, z, *thetas)
    assert answers and res.ok, res.reason
    t = np.linspace(0.0, planner.config.duration_s, 121)
    q, v, _ = res.evaluate(t)
    jp = robot.joint_params
    assert np.all(q >= jp.position_lower) and np.all(q <= jp.position_upper)
    assert np.all(np.abs(v) <= jp.velocity_limit)
    scene = DrakeScene(robot, payload, [])
    floor = min(scene.distances(qi)[1] for qi in q)
    assert floor > 0.0, f"the adopted plan reaches {-floor:.3f} m into the floor"
    if violated == "floor":  # the target itself does reach into the floor: the check had work to do
        qt, _, _ = planner.problem(Q0, z, z, *thetas, certify_torque=False).desired_at(t, np.asarray(target))
        assert min(scene.distances(qi)[1] for qi in qt) < 0.0


def test_a_clearance_within_its_rounding_is_not_feasible(robot, payload):
    """is_feasible rounds outward: a kept pair whose float clearance is >= 0 but below what the
    rounding of its signed distance may add is refused; twice that margin is accepted."""
    planner, thetas = make_planner(robot, payload, scene_obstacles())
    z = np.zeros(7)
    prob = planner.problem(Q0, z, z, *thetas)
    k = np.clip(z, prob.k_lo, prob.k_hi)
    vals, _, pts = prob._pair_values(k, with_jacobian=False)
    margin = prob.clearance_rounding(pts)
    assert len(vals) and np.all(margin > 0) and np.all(margin < 1e-12)  # of the order of eps x metres
    i = int(np.argmin(vals))
    need = prob.pair_need.copy()
    for scale, feasible in ((0.5, False), (2.0, True)):
        prob.pair_need = need.copy()
        prob.pair_need[i] = need[i] + vals[i] - scale * margin[i]  # pair i's clearance: scale x its margin
        assert 0.0 <= prob.collision(k, with_jacobian=False)[0][i]
        assert prob.is_feasible(k) is feasible
