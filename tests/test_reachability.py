"""Every over-approximation of systems/planner/reachability.py contains what it claims to contain."""

import numpy as np
import pytest
from helpers import mass_matrices
from safesysid.systems.math.intervals import Interval
from safesysid.systems.model.payload import load_dumbbells
from safesysid.systems.model.robot_model import MODELS_DIR
from safesysid.systems.planner import interval_dynamics as idyn
from safesysid.systems.planner import reachability as reach
from safesysid.systems.planner import torque_certificate as tcert


@pytest.fixture(scope="module")
def spheres(robot):
    db = load_dumbbells(MODELS_DIR / "dumbbells.yaml")["8lb"]
    return reach.arm_spheres(robot).concat(reach.payload_spheres(robot, db))


def test_interval_passivity_regressor_is_exact_on_points_and_encloses_boxes(robot):
    rng = np.random.default_rng(0)
    n = robot.n
    q, v, va, aa = (rng.normal(size=(6, n)) for _ in range(4))
    point = robot.passivity_regressor(q, v, va, aa)
    wp = idyn.interval_passivity_regressor(robot, *(Interval(x) for x in (q, v, va, aa)))
    assert np.all(wp.lo <= point + 1e-9) and np.all(point <= wp.hi + 1e-9)
    assert np.max(wp.hi - wp.lo) < 1e-9  # degenerate boxes give the point regressor
    # Random boxes: every sampled point inside the box has its regressor inside the enclosure.
    mids = [rng.normal(size=(16, n)) for _ in range(4)]
    rads = [rng.uniform(0, r, size=(16, n)) for r in (0.2, 0.5, 0.5, 1.0)]
    boxes = [Interval(m - r, m + r) for m, r in zip(mids, rads)]
    wp = idyn.interval_passivity_regressor(robot, *boxes)
    for _ in range(30):
        x = [m + r * rng.uniform(-1, 1, size=m.shape) for m, r in zip(mids, rads)]
        w = robot.passivity_regressor(*x)
        tol = 1e-10 * (1 + np.abs(w))
        assert np.all(wp.lo - tol <= w) and np.all(w <= wp.hi + tol)
    # ... including the corners, where interval bounds are usually attained.
    x = [m + r * np.sign(rng.normal(size=m.shape)) for m, r in zip(mids, rads)]
    w = robot.passivity_regressor(*x)
    assert np.all(wp.lo - 1e-10 * (1 + np.abs(w)) <= w) and np.all(w <= wp.hi + 1e-10 * (1 + np.abs(w)))


def test_spheres_come_from_the_sphere_file_and_ride_on_drake_body_poses(robot, spheres):
    """Each sphere of the planner's file, placed on its link by Drake, is where sphere_centres
    puts it (the enclosure of the link shapes is tests/test_collision_geometry.py)."""
    import yaml
    from safesysid.systems.model.robot_model import make_plant

    plant, _, _ = make_plant(robot.source)
    plant.Finalize()
    ctx = plant.CreateDefaultContext()
    arm = reach.arm_spheres(robot)
    links = yaml.safe_load((MODELS_DIR / "kinova_gen3_spheres.yaml").read_text())["links"]
    listed = [(link, s["centre_m"]) for link, group in links.items() for s in group]
    assert len(arm) == len(listed) > 10
    rng = np.random.default_rng(1)
    for _ in range(5):
        q = rng.uniform(-2, 2, robot.n)
        plant.SetPositions(ctx, q)
        c, _ = reach.sphere_centres(robot.tree, arm, q[None], with_jacobian=False)
        for s, (link, centre) in enumerate(listed):
            expected = plant.EvalBodyPoseInWorld(ctx, plant.GetBodyByName(link)) @ np.asarray(centre, float)
            assert np.allclose(expected, c[0, s], atol=1e-12)


def test_sphere_jacobian_and_global_lipschitz_bound(robot, spheres):
    rng = np.random.default_rng(2)
    lips = reach.sphere_lipschitz(robot.tree, spheres)
    q = rng.uniform(-3, 3, size=(200, robot.n))
    c, jac = reach.sphere_centres(robot.tree, spheres, q)
    h = 1e-6
    for j in range(robot.n):
        dq = np.zeros(robot.n)
        dq[j] = h
        cp, _ = reach.sphere_centres(robot.tree, spheres, q[:5] + dq, with_jacobian=False)
        cm, _ = reach.sphere_centres(robot.tree, spheres, q[:5] - dq, with_jacobian=False)
        assert np.allclose((cp - cm) / (2 * h), jac[:5, :, j], atol=1e-8)
    norms = np.linalg.norm(jac, axis=-1)  # (N, m, n)
    assert np.all(norms <= lips[None] + 1e-12)
    assert np.max(norms / np.where(lips > 0, lips, 1)) > 0.6  # the bound is not wildly loose


def test_box_signed_distance_and_gradient():
    from pydrake.math import RollPitchYaw

    rng = np.random.default_rng(3)
    rot = RollPitchYaw([0.3, -0.2, 1.1]).ToRotationMatrix().matrix()
    centre, half = np.array([0.5, -0.1, 0.3]), np.array([0.1, 0.2, 0.05])
    pts = centre + rng.uniform(-0.5, 0.5, size=(400, 3))
    bc = lambda x: (  # noqa: E731
        np.broadcast_to(centre, x.shape),
        np.broadcast_to(rot, x.shape + (3,)),
        np.broadcast_to(half, x.shape),
    )
    sd, grad = reach.box_signed_distance(pts, *bc(pts))
    # Brute force: outside, the distance to a dense sampling of the box surface is never smaller.
    local = (pts - centre) @ rot
    inside = np.all(np.abs(local) <= half, axis=1)
    assert np.all((sd <= 0) == inside)
    dense = rng.uniform(-1, 1, size=(20000, 3)) * half
    world = centre + dense @ rot.T
    d = np.linalg.norm(pts[~inside, None] - world[None], axis=-1).min(1)
    assert np.all(sd[~inside] <= d + 1e-12) and np.all(d - sd[~inside] < 0.02)
    h = 1e-7
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = h
        fd = (reach.box_signed_distance(pts + e, *bc(pts))[0] - reach.box_signed_distance(pts - e, *bc(pts))[0]) / (
            2 * h
        )
        assert np.allclose(fd, grad[:, axis], atol=1e-5)


def _reach(robot, rng, bounds=None, v_scale=0.5, a_scale=0.5):
    q0 = rng.uniform(-1, 1, robot.n)
    v0 = rng.uniform(-v_scale, v_scale, robot.n)
    a0 = rng.uniform(-a_scale, a_scale, robot.n)
    kr = np.array([np.pi / 48] * 4 + [np.pi / 20] * 3)
    bounds = bounds or reach.TrackingBounds.from_ultimate_bound(0.02, 8.0, 5.0, n=robot.n, alpha=20.0)
    return reach.PlanReach(q0, v0, a0, 3.0, np.zeros(robot.n), kr, 64, bounds)


def test_joint_boxes_contain_the_continuous_trajectory_with_tracking_error(robot):
    rng = np.random.default_rng(4)
    for _ in range(4):
        r = _reach(robot, rng)
        t = np.linspace(0, r.T, 6401)
        idx = np.minimum(np.searchsorted(r.edges, t, side="right") - 1, len(r.t_mid) - 1)
        for _ in range(5):
            k = rng.uniform(-1, 1, robot.n)
            q, _, _ = r.bezier.evaluate(t, r.q_end(k))
            err = rng.uniform(-1, 1, q.shape) * r.bounds.position
            dev = np.abs(q + err - r.q_mid(k)[idx])
            assert np.all(dev <= r.rho[idx])
        # not vacuous: the radius is attained up to the tracking part within a few percent
        assert np.max(np.abs(q - r.q_mid(k)[idx]) / (r.rho[idx] - r.bounds.position + 1e-15)) > 0.5


def test_state_boxes_contain_every_k_time_and_tracking_error(robot):
    rng = np.random.default_rng(5)
    r = _reach(robot, rng)
    k_lo, k_hi = -0.5 * np.ones(robot.n), np.ones(robot.n)
    qb, vb, vab, aab = r.state_boxes(k_lo, k_hi)
    t = np.linspace(0, r.T, 3001)
    idx = np.minimum(np.searchsorted(r.edges, t, side="right") - 1, len(r.t_mid) - 1)
    b = r.bounds
    for _ in range(10):
        k = rng.uniform(k_lo, k_hi)
        q, v, a = r.bezier.evaluate(t, r.q_end(k))
        u = lambda: rng.uniform(-1, 1, q.shape)  # noqa: E731, B023 (used in this iteration only)
        for box, x in (
            (qb, q + u() * b.position),
            (vb, v + u() * b.velocity),
            (vab, v + u() * b.qd_a),
            (aab, a + u() * b.qdd_a),
        ):
            assert np.all(box.lo[idx] <= x) and np.all(x <= box.hi[idx])


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_limit_box_keeps_position_and_velocity_limits_and_is_not_vacuous(robot, side):
    """Joint 2 close to its upper (side +1) or lower (-1) limit and moving toward it, joint 5 fast
    toward its velocity limit: every k of the box keeps both limits with the tube's margins, and the
    edge of the box comes within 2 mrad of the limit."""
    rng = np.random.default_rng(6)
    jp = robot.joint_params
    b = reach.TrackingBounds.from_ultimate_bound(0.02, 8.0, 5.0, n=robot.n, alpha=20.0)
    limit = jp.position_upper if side > 0 else jp.position_lower
    q0 = np.zeros(robot.n)
    q0[1] = limit[1] - side * 0.05  # joint 2 close to its limit, moving toward it
    v0 = np.zeros(robot.n)
    v0[1] = side * 0.05
    v0[4] = side * (jp.velocity_limit[4] - 0.3)  # joint 5 fast
    kr = np.array([np.pi / 48] * 4 + [np.pi / 20] * 3)
    r = reach.PlanReach(q0, v0, np.zeros(robot.n), 3.0, np.zeros(robot.n), kr, 128, b)
    k_lo, k_hi, why = r.limit_box(jp)
    assert why == ""
    assert (k_hi if side > 0 else -k_lo)[1] < 1.0  # the limit binds
    t = np.linspace(0, 3.0, 30001)
    worst_q = -np.inf
    for k in [k_lo, k_hi] + [rng.uniform(k_lo, k_hi) for _ in range(20)]:
        q, v, _ = r.bezier.evaluate(t, r.q_end(k))
        assert np.all(q + b.position <= jp.position_upper) and np.all(q - b.position >= jp.position_lower)
        assert np.all(np.abs(v) + b.velocity <= jp.velocity_limit)
        worst_q = max(worst_q, (side * q[:, 1] + b.position[1]).max())
    # At the edge of the box the trajectory comes within 2 mrad of the limit: not vacuous.
    assert side * limit[1] - worst_q < 2e-3
    # A start already past the shrunk limit is reported, not planned.
    q_bad = q0.copy()
    q_bad[1] = limit[1] - side * 0.5 * b.position[1]
    r_bad = reach.PlanReach(q_bad, np.zeros(robot.n), np.zeros(robot.n), 3.0, np.zeros(robot.n), kr, 128, b)
    k_lo, _, why = r_bad.limit_box(jp)
    assert k_lo is None and "joint 2" in why


def test_limit_box_keeps_the_velocity_margin_on_both_sides(robot):
    """A 1 s plan from rest whose wide k range for joint 5 would exceed its velocity limit: the box
    stops both ends exactly where the speed plus the tube's velocity bound reaches the limit."""
    jp = robot.joint_params
    b = reach.TrackingBounds.from_ultimate_bound(0.02, 8.0, 5.0, n=robot.n, alpha=20.0)
    kr = np.array([np.pi / 48] * 4 + [1.0] + [np.pi / 20] * 2)
    z = np.zeros(robot.n)
    r = reach.PlanReach(z, z, z, 1.0, z, kr, 128, b)
    k_lo, k_hi, why = r.limit_box(jp)
    assert why == "" and -1.0 < k_lo[4] < 0.0 < k_hi[4] < 1.0  # the velocity limit binds both ways
    t = np.linspace(0, 1.0, 20001)
    for k in (k_lo, k_hi):
        _, v, _ = r.bezier.evaluate(t, r.q_end(k))
        excess = np.abs(v).max(0) + b.velocity - jp.velocity_limit
        assert np.all(excess <= 0) and excess[4] > -1e-6


def tube_boundary_states(robot, rng, desired, bounds, gains, box, count):
    """States ON the boundary of the tracking tube around each desired state (q_d, qd_d, qdd_d)
    (rows of `desired`): the position error e anywhere in its bound (entries at +-bound half the
    time), theta_true in [theta] (a box vertex half the time), r in a random direction (along one
    joint half the time) scaled so that the TRUE Lyapunov value 1/2 r^T M(q; theta_true) r equals
    V_max, edot = r - Kr e.
    Returns [(row, q, qd, theta_true, M(q; theta_true))]."""
    n = robot.n
    qd, vd, _ = desired
    drawn = []  # the random draws first, in the order they always had; the true M in one batch
    for row in range(len(qd)):
        for _ in range(count):
            e = rng.uniform(-1, 1, n)
            e = np.where(rng.uniform(size=n) < 0.5, np.sign(e), e) * bounds.position / (1 + 1e-12)
            theta_true = rng.uniform(box.lo, box.hi)
            if rng.uniform() < 0.5:
                theta_true = np.where(rng.uniform(size=theta_true.size) < 0.5, box.lo, box.hi)
            u = rng.normal(size=n)
            if rng.uniform() < 0.5:  # along one joint: |v_j| = lambda there
                u = np.eye(n)[rng.integers(n)] * np.sign(u[0])
            drawn.append((row, qd[row] - e, e, theta_true, u))
    m_true = mass_matrices(robot, np.array([d[1] for d in drawn]), np.array([d[3] for d in drawn]))
    states = []
    for (row, q, e, theta_true, u), m in zip(drawn, m_true):
        r = u * np.sqrt(2 * gains.V_max / (u @ m @ u))
        states.append((row, q, vd[row] - (r - gains.Kr * e), theta_true, m))
    return states


def tube_boxes(desired, bounds):
    """The planner's state boxes (q, qd, qd_a, qdd_a) of the tube alone around each desired state:
    the smallest boxes the planner's bound must be valid on (no time or k spread)."""
    qd, vd, ad = desired
    pad = lambda x, rad: Interval(x - rad, x + rad)  # noqa: E731
    return pad(qd, bounds.position), pad(vd, bounds.velocity), pad(vd, bounds.qd_a), pad(ad, bounds.qdd_a)


def planner_torque_bound(robot, boxes, theta0, box, bounds):
    """(sup|u| (N, n), robust term (N, n), excess (N, n)) of the planner on state boxes (q, qd, qd_a, qdd_a)."""
    wp = idyn.interval_passivity_regressor(robot, *boxes)
    excess = tcert.barrier_excess(robot, boxes[0], box.lo, box.hi, bounds)
    sup, _, robust = tcert.torque_bound(wp, theta0, box.lo, theta_hi=box.hi, excess=excess)
    return sup, robust, excess


def table_ii_setup(robot, V_max):
    """(scenario, theta0, [theta], gains, tracking bounds): the default scenario's controller at
    V_max with the Table II prior (rest of the robot +-5 %)."""
    from safesysid.scenario import load_scenario
    from safesysid.systems.controller import armour as ctl
    from safesysid.systems.model import uncertainty

    s = load_scenario()
    ii = s.initial_interval
    theta0, box = uncertainty.parameter_box(robot, np.array(ii.nominal), np.array(ii.lower), np.array(ii.upper))
    gains = ctl.ArmourGains(Kr=np.array(s.controller.Kr, float), alpha=s.controller.alpha, V_max=V_max)
    return s, theta0, box, gains, ctl.tracking_bounds_for(robot, gains, box.lo)


def random_plan(s, rng, bounds, intervals=8):
    """A plan family from a random moving state near the scenario's start (its k ranges)."""
    n = len(s.q0_rad)
    q0 = np.array(s.q0_rad) + rng.uniform(-0.5, 0.5, n)
    v0, a0 = rng.uniform(-0.3, 0.3, n), rng.uniform(-0.5, 0.5, n)
    return reach.PlanReach(q0, v0, a0, 3.0, np.zeros(n), np.array(s.planner.k_range_rad), intervals, bounds)


@pytest.mark.parametrize("V_max", [0.005, 0.02])
def test_torque_bound_covers_the_controller_command_on_the_whole_tube(robot, V_max):
    """The planner's robust term and sup|u| >= |v_j|, |u_j| of the actual ARMOUR law
    (systems/controller/armour.py) on the BOUNDARY of the tube (true V = V_max), where the box bound
    V_bar exceeds V_max (h < 0) and lambda exceeds |w_bar|. Quickstart Table II prior, desired
    states of random plans; the planner's bound evaluated on two boxes that contain each state:
    the tube alone around its desired state, and the state itself (a degenerate box: no slack)."""
    from safesysid.systems.controller import armour as ctl

    rng = np.random.default_rng(7)
    n = robot.n
    s, theta0, box, gains, bounds = table_ii_setup(robot, V_max)
    dyn = ctl.ControllerDynamics(robot)
    plans = [random_plan(s, rng, bounds) for _ in range(8)]
    desired = [
        np.concatenate(x)
        for x in zip(*(p.bezier.evaluate(rng.uniform(0, 3.0, 5), p.q_end(rng.uniform(-1, 1, n))) for p in plans))
    ]  # 40 desired states
    sup_tube, robust_tube, _ = planner_torque_bound(robot, tube_boxes(desired, bounds), theta0, box, bounds)
    rows, outs = [], []
    for i, q, v, _, m_true in tube_boundary_states(robot, rng, desired, bounds, gains, box, 12):
        out = ctl.armour_control(dyn, gains, q, v, desired[0][i], desired[1][i], desired[2][i], theta0, box)
        assert 0.5 * out.err.r @ m_true @ out.err.r == pytest.approx(V_max, rel=1e-9)  # on the boundary
        rows.append(i)
        outs.append(out)
    states = [
        np.array(x)
        for x in zip(
            *(
                (q, v, o.err.qd_a, o.err.qdd_a)
                for o, (q, v) in zip(
                    outs, ((desired[0][i] - o.err.e, desired[1][i] - o.err.edot) for i, o in zip(rows, outs))
                )
            )
        )
    ]
    sup_point, robust_point, excess = planner_torque_bound(robot, [Interval(x) for x in states], theta0, box, bounds)
    v = np.abs([o.v for o in outs])
    u = np.abs([o.u for o in outs])
    h = np.array([o.h for o in outs])
    over = np.array([o.lam - np.linalg.norm(o.w_bar) for o in outs])
    # what |v_j| = lambda |r_j|/|r| takes beyond |w_bar| on joint j (the per-joint barrier excess covers it)
    over_j = over[:, None] * np.abs([o.err.r / np.linalg.norm(o.err.r) for o in outs])
    print(
        f"V_max {V_max}: {len(outs)} boundary states, {np.sum(h < 0)} with h < 0, lambda - |w_bar| up to "
        f"{over.max():.3f} N m; max |v_j| - robust term {np.max(v - robust_point):+.3f} N m on the state's own box, "
        f"{np.max(v - robust_tube[rows]):+.3f} N m on the tube box; max |u_j| / sup {np.max(u / sup_point):.4f} "
        f"(own box), {np.max(u / sup_tube[rows]):.4f} (tube box); max (lambda - |w_bar|) / barrier excess "
        f"{np.max(over_j / excess):.3f}"
    )
    assert np.sum(h < 0) > 0.3 * len(h)  # the states the old bound missed are sampled
    assert np.all(v <= robust_point) and np.all(v <= robust_tube[rows])
    assert np.all(u <= sup_point) and np.all(u <= sup_tube[rows])
    assert np.max(over_j / excess) > 0.2  # the extra term is needed and not absurdly loose


def test_body_jacobians_rebuild_the_mass_matrix(robot):
    """sum_i (J_i r)^T I_i (J_i r) + sum_j Ia_j r_j^2 = r^T M r (RobotModel.mass_matrix) with the
    interval body Jacobians at degenerate boxes and the inertia quadratic forms."""
    rng = np.random.default_rng(10)
    n = robot.n
    q = rng.uniform(-np.pi, np.pi, (5, n))
    jac = idyn.interval_body_jacobians(robot.tree, Interval(q))
    assert np.max(jac.hi - jac.lo) < 1e-12
    for row in range(len(q)):
        r = rng.normal(size=n)
        twists = np.einsum("ijc,j->ic", jac.mid[row], r)  # (bodies, 6)
        energy = sum(
            twists[i] @ np.einsum("kab,k->ab", idyn._INERTIA_FORMS, robot.theta[10 * i : 10 * i + 10]) @ twists[i]
            for i in range(n)
        )
        energy += robot.theta[10 * n + 2 :: 4] @ r**2
        assert energy == pytest.approx(r @ robot.mass_matrix(q[row][None])[0] @ r, rel=1e-12)
    # The tests' batched truth (helpers.mass_matrices), per-row theta, is RobotModel.mass_matrix.
    thetas = robot.theta * rng.uniform(0.5, 1.5, (len(q), robot.theta.size))
    batched = mass_matrices(robot, q, thetas)
    for row in range(len(q)):
        np.testing.assert_allclose(
            batched[row], robot.mass_matrix(q[row][None], thetas[row])[0], rtol=1e-12, atol=1e-12
        )


def test_interval_mass_spread_encloses_the_point_spread(robot):
    """interval_mass_spread over a configuration box >= controller.mass_spread at every sampled
    configuration of it (corners included); equal to it on degenerate boxes; tight on small boxes."""
    from safesysid.scenario import load_scenario
    from safesysid.systems.controller import armour as ctl
    from safesysid.systems.model import uncertainty

    rng = np.random.default_rng(11)
    n = robot.n
    ii = load_scenario().initial_interval  # the Gen3's declared prior: Table II
    _, box = uncertainty.parameter_box(robot, np.array(ii.nominal), np.array(ii.lower), np.array(ii.upper))
    centre = rng.uniform(-2, 2, (12, n))
    point = np.array([ctl.mass_spread(robot, q, box.lo, theta_hi=box.hi) for q in centre])
    np.testing.assert_allclose(idyn.interval_mass_spread(robot, Interval(centre), box.lo, box.hi), point, rtol=1e-9)
    assert np.all(idyn.interval_mass_spread(robot, Interval(centre), box.lo, box.hi) >= point)
    for rad_max, loose in ((0.02, 1.3), (0.15, None)):
        rad = rng.uniform(0, rad_max, centre.shape)
        mu = idyn.interval_mass_spread(robot, Interval(centre - rad, centre + rad), box.lo, box.hi)
        worst = np.zeros(len(centre))
        for _ in range(15):
            pick = rng.uniform(-1, 1, centre.shape)
            pick = np.where(rng.uniform(size=centre.shape) < 0.5, np.sign(pick), pick)
            sampled = np.array([ctl.mass_spread(robot, q, box.lo, theta_hi=box.hi) for q in centre + pick * rad])
            assert np.all(sampled <= mu)
            worst = np.maximum(worst, sampled)
        print(
            f"boxes up to +-{rad_max} rad: interval mu / sampled max {np.min(mu / worst):.3f}-{np.max(mu / worst):.3f}"
        )
        if loose:
            assert np.max(mu / worst) < loose


def test_local_spread_bounds_sphere_motion_on_joint_boxes(robot, spheres):
    rng = np.random.default_rng(8)
    n = robot.n
    lips = reach.sphere_lipschitz(robot.tree, spheres)
    q_c = rng.uniform(-2, 2, size=(40, n))
    rho = rng.uniform(0.0, 0.08, size=(40, n))
    c, jac = reach.sphere_centres(robot.tree, spheres, q_c)
    spread = reach.local_spread(robot.tree, lips, np.linalg.norm(jac, axis=-1), rho=rho, reach_radius=rho)
    assert np.all(spread <= rho @ lips.T + 1e-12)  # never worse than the global bound
    worst = 0.0
    for _ in range(60):
        pick = rng.uniform(-1, 1, size=q_c.shape)
        pick = np.where(rng.uniform(size=q_c.shape) < 0.5, np.sign(pick), pick)  # many corners
        cq, _ = reach.sphere_centres(robot.tree, spheres, q_c + pick * rho, with_jacobian=False)
        moved = np.linalg.norm(cq - c, axis=-1)
        assert np.all(moved <= spread)
        worst = max(worst, np.max(moved / spread))
    assert worst > 0.5  # and reasonably tight


def test_vertex_robust_bound_is_sound_and_tighter(robot):
    """w_bar from the aa-vertex refinement >= sum_k |Wp_ik| d_k at sampled points (aa at box
    vertices, where the maximum sits) and <= the plain interval bound."""
    from safesysid.scenario import load_scenario

    rng = np.random.default_rng(9)
    n = robot.n
    ii = load_scenario().initial_interval  # the Gen3's declared prior: Table II
    theta0 = robot.theta.copy()
    rel = 0.05 * np.abs(theta0)
    lo, hi = theta0 - rel, theta0 + rel
    sl = robot.ee_slice
    theta0[sl], lo[sl], hi[sl] = ii.nominal, ii.lower, ii.upper
    d = np.maximum(hi - theta0, theta0 - lo)
    mids = [
        rng.uniform(-1, 1, (6, n)),
        rng.uniform(-0.5, 0.5, (6, n)),
        rng.uniform(-0.5, 0.5, (6, n)),
        rng.uniform(-1, 1, (6, n)),
    ]
    rads = [np.full((6, n), 0.02), np.full((6, n), 0.15), np.full((6, n), 0.07), np.full((6, n), 0.8)]
    boxes = [Interval(m - r, m + r) for m, r in zip(mids, rads)]
    wv, plain = tcert.robust_bound_vertex(robot, *boxes, theta0, lo, hi, sl)
    assert np.all(wv <= plain) and np.mean(wv) < 0.95 * np.mean(plain)
    worst = 0.0
    for _ in range(40):
        x = [m + r * rng.uniform(-1, 1, m.shape) for m, r in zip(mids, rads)]
        x[3] = mids[3] + rads[3] * np.sign(rng.normal(size=mids[3].shape))  # aa at vertices
        wbar = np.abs(robot.passivity_regressor(*x)) @ d
        assert np.all(wbar <= wv * (1 + 1e-12))
        worst = max(worst, np.max(wbar / wv))
    assert worst > 0.5
