"""The affine (zonotope) torque certificate of the planner (systems/planner/affine_forms.py,
interval_dynamics.affine_passivity_regressor / affine_torque_bound) contains what the ARMOUR law
does on every REACHABLE tube state, with the states ON the boundary (true V = V_max, h < 0) and
the tracking error produced by the error filter itself (de/dt = r - Kr e, e(0) = 0, |r| <= eps),
so |Kr e|_2 <= kappa eps as the certificate assumes; certified >= sampled everywhere."""

import numpy as np
import pytest
from helpers import mass_matrices
from safesysid.systems.math.intervals import Interval
from safesysid.systems.planner import affine_forms as aff
from safesysid.systems.planner import interval_dynamics as idyn
from safesysid.systems.planner import torque_certificate as tcert


def test_filter_gain_is_the_integral_of_the_envelope():
    from scipy.integrate import quad

    for kr in ([5.0] * 4 + [7.0] * 3, [1.0, 2.0, 4.0], [3.0, 3.0], [2.0, 9.0, 5.0, 5.5]):
        exact = quad(lambda t, kr=kr: max(k * np.exp(-k * t) for k in kr), 0, 60, limit=500)[0]
        gain = aff.filter_gain(kr)
        assert exact * (1 - 1e-7) <= gain <= exact * (1 + 1e-6)  # quad's own error ~1e-9 at the kinks
    t_cross = np.log(7 / 5) / 2  # two gains: 7 e^{-7t} above 5 e^{-5t} until t_cross
    assert aff.filter_gain([5.0] * 4 + [7.0] * 3) >= 1 - np.exp(-7 * t_cross) + np.exp(-5 * t_cross)
    assert aff.filter_gain([5.0] * 7) == pytest.approx(1.0)


def filtered_error(rng, kr, eps, steady=None):
    """e(t) of de/dt = r - Kr e from e(0) = 0 under a piecewise-constant r(t) with |r| = eps (the
    largest the tube allows): random directions and durations, or (steady) one direction held long."""
    n = len(kr)
    e = np.zeros(n)
    pieces = [(steady, 5.0)] if steady is not None else [(rng.normal(size=n), rng.uniform(0.02, 0.6)) for _ in range(6)]
    for direction, h in pieces:
        r = eps * direction / np.linalg.norm(direction)
        decay = np.exp(-kr * h)
        e = decay * e + (1 - decay) * r / kr
    return e


def tube_samples(robot, rng, plan, k_lo, k_hi, gains, bounds, box, count):
    """(interval, q, qd, q_d, qd_d, qdd_d) ON the tube boundary at random t in each interval and k in
    the box: e from the filter (steady along one joint a third of the time), r along one joint half
    the time, along the worst barrier-excess direction of a joint a quarter of the time, scaled to
    the TRUE V = V_max (or |r| = eps) with theta_true at the box vertex making h most negative."""
    n = robot.n
    for i in range(len(plan.t_mid)):
        for c in range(count):
            t = rng.uniform(plan.edges[i], plan.edges[i + 1])
            q_d, qd_d, qdd_d = (x[0] for x in plan.bezier.evaluate([t], plan.q_end(rng.uniform(k_lo, k_hi))))
            steady = np.eye(n)[rng.integers(n)] * rng.choice([-1, 1]) if c % 3 == 0 else None
            e = filtered_error(rng, gains.Kr, bounds.eps, steady) / (1 + 1e-9)
            q = q_d - e
            if c % 4 == 1:  # the direction where joint j sees the most barrier excess: |u_j| u^T dM u spread
                j, cand = rng.integers(n), rng.normal(size=(300, n))
                cand /= np.linalg.norm(cand, axis=1, keepdims=True)
                rows = np.einsum("ci,cik->ck", cand, robot.momentum_regressor(np.repeat(q[None], 300, 0), cand))
                u = cand[np.argmax(np.abs(cand[:, j]) * (np.abs(rows) @ (box.hi - box.lo)))]
            else:
                u = np.eye(n)[rng.integers(n)] * rng.choice([-1, 1]) if c % 2 == 0 else rng.normal(size=n)
            row = u @ robot.momentum_regressor(q[None], u[None])[0]
            theta_true = np.where(row >= 0, box.lo, box.hi)
            u = u / np.linalg.norm(u)
            # |r| <= eps holds for a physically consistent truth (M >= sigma_min I); a box vertex may not
            # be one, so its V = V_max could need |r| > eps: capped there (still the tube's edge)
            r = u * min(np.sqrt(2 * gains.V_max / (u @ mass_matrices(robot, q, theta_true)[0] @ u)), bounds.eps)
            yield i, q, qd_d - (r - gains.Kr * e), q_d, qd_d, qdd_d


@pytest.mark.parametrize("V_max", [0.005, 0.02])
def test_affine_torque_bound_covers_the_controller_on_reachable_tube_states(robot, V_max):
    from safesysid.systems.controller import armour as ctl
    from test_reachability import random_plan, table_ii_setup

    rng = np.random.default_rng(31)
    n = robot.n
    s, theta0, box, gains, bounds = table_ii_setup(robot, V_max)
    dyn = ctl.ControllerDynamics(robot)
    worst_u, worst_w, worst_x, negative, total, entries_out = 0.0, 0.0, 0.0, 0, 0, 0
    for _ in range(4):
        plan = random_plan(s, rng, bounds)
        k_lo, k_hi = -0.25 * np.ones(n), 0.25 * np.ones(n)
        states = plan.tube_states(k_lo, k_hi)
        wp = idyn.affine_passivity_regressor(robot, *states)
        excess = tcert.barrier_excess(robot, Interval(states[0].lo, states[0].hi), box.lo, box.hi, bounds)
        sup, _, robust = tcert.affine_torque_bound(wp, theta0, box.lo, theta_hi=box.hi, excess=excess)
        for i, q, v, q_d, qd_d, qdd_d in tube_samples(robot, rng, plan, k_lo, k_hi, gains, bounds, box, 12):
            out = ctl.armour_control(dyn, gains, q, v, q_d, qd_d, qdd_d, theta0, box)
            point = robot.passivity_regressor(*(x[None] for x in (q, v, out.err.qd_a, out.err.qdd_a)))[0]
            tol = 1e-10 * (1 + np.abs(point))
            entries_out += np.sum((point < wp.lo[i] - tol) | (point > wp.hi[i] + tol))
            assert np.all(np.abs(out.u) <= sup[i]) and np.all(np.abs(out.v) <= robust[i])
            worst_u = max(worst_u, np.max(np.abs(out.u) / sup[i]))
            worst_w = max(worst_w, np.linalg.norm(out.w_bar) / (robust[i].min() - excess[i].max()))
            # lambda's excess over |w_bar| as joint j sees it (|v_j| = lambda |r_j|/|r|): <= excess_j
            over = (out.lam - np.linalg.norm(out.w_bar)) * np.abs(out.err.r) / np.linalg.norm(out.err.r)
            assert np.all(over <= excess[i])
            worst_x = max(worst_x, np.max(over / excess[i]))
            negative += out.h < 0
            total += 1
    print(
        f"V_max {V_max}: {total} reachable boundary states, {negative} with h < 0; max |u_j| / certified "
        f"{worst_u:.3f}; max |w_bar| / certified |w_bar| {worst_w:.3f}; max excess seen by a joint / "
        f"certified excess_j {worst_x:.3f}"
    )
    assert entries_out == 0  # every regressor entry inside its affine enclosure
    assert negative > 0.5 * total
    assert worst_u > 0.5 and worst_w > 0.5 and worst_x > 0.4  # tight enough to matter


def test_the_error_cap_is_used_and_needed(robot):
    """A tracking error at every corner of its per-joint bound at once is NOT reachable (|Kr e| =
    sqrt(7) eps > kappa eps) and the affine forms exclude it: the cap carries real information."""
    from safesysid.systems.controller import armour as ctl

    n = robot.n
    gains = ctl.ArmourGains(np.array([5.0] * 4 + [7.0] * 3), 20.0, 0.02)
    bounds = ctl.tracking_bounds_for(robot, gains, robot.theta)
    q = Interval(np.zeros((1, n)))
    states = aff.tube_states(q, Interval(np.zeros((1, n))), Interval(np.zeros((1, n))), bounds)
    va = states[2]  # qd_a = Kr e: with every |e_i| at its bound, |qd_a|_2 = sqrt(7) eps
    assert np.linalg.norm(gains.Kr * bounds.position) > 2 * bounds.eps
    direction = np.ones(n) / np.sqrt(n)
    along = va.c[0] @ direction + va.spread(np.einsum("js,j->s", va.g[0], direction))
    assert along <= aff.filter_gain(gains.Kr) * bounds.eps * (1 + 1e-9)
    assert along < 0.5 * np.linalg.norm(gains.Kr * bounds.position)  # the box alone would allow 2.6 eps
