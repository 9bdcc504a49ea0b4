"""Certified margin vs sampled worst case, per constraint family, at the hardware V_max = 0.02.

The starts of bench_torque_feasibility.py (10 random starts near the default pose, 3 boxes near
the arm, 4 lb payload, Table II prior, first plan from rest). For each start, on the k box the
planner tries last (the allowed box shrunk by 2^-torque_shrink_steps toward k = 0) and at the
(time interval, joint) where the certified torque bound (the affine enclosure the planner uses) is
worst, the bound's terms, and the total of the interval-box bound used before (plain / aa-vertex):
    nominal   sup |W_p theta0| over the interval's state box (desired states + tracking tube)
    w_bar     ||w_bar||_2, the parameter interval's disturbance bound (best of plain / aa-vertex)
    excess    (alpha/2) eps mu_j, lambda's excess over ||w_bar|| as joint j sees it (|v_j| = lambda |r_j|/|r|)
and, next to each, the largest value the actual ARMOUR law (systems/controller/armour.py) produces on
states ON the tube boundary inside that interval (t and k in the box, e reachable: the output of
the error filter under |r| = eps, r along the joint (where |v_j| = lambda) or random, theta_true
at the box vertex that makes h most negative). Also the collision spread (certified vs sampled centre motion) and the
joint-limit box. `python benchmarks/bench_reach_margins.py [V_max ...]` prints a JSON table.
"""

from __future__ import annotations

import json
import sys

import numpy as np


def sampled_command(robot, dyn, gains, desired, bounds, theta0, box, joint, rng, count):
    """Largest |tau_nom_j|, ||w_bar||, lambda - ||w_bar||, |v_j|, |u_j| of the ARMOUR law over
    `count` tube-boundary states around each desired state (rows of `desired`)."""
    from safesysid.systems.controller import armour as ctl

    n = robot.n
    worst = np.zeros(5)
    for qd, vd, ad in zip(*desired):
        for c in range(count):
            e = filtered_error(rng, gains.Kr, bounds.eps, np.eye(n)[joint] if c % 3 == 0 else None) / (1 + 1e-9)
            q = qd - e
            u = np.eye(n)[joint] if c % 2 == 0 else rng.normal(size=n)
            u = u / np.linalg.norm(u)
            row = u @ robot.momentum_regressor(q[None], u[None])[0]  # u^T dM/dtheta_k u
            theta_true = np.where(row >= 0, box.lo, box.hi)  # smallest true V for this r: h most negative
            m_true = robot.mass_matrix(q[None], theta_true)[0]
            r = u * min(np.sqrt(2 * gains.V_max / (u @ m_true @ u)), bounds.eps)  # |r| <= eps (physical truth)
            tau0 = dyn.regressors(q, vd - (r - gains.Kr * e), vd + gains.Kr * e, aa=ad, x=np.zeros(n))[0] @ theta0
            sign = np.sign(tau0[joint]) or 1.0
            r = r * sign * np.sign(r[joint] or 1.0)  # |u_j| largest when v_j adds to tau_nom_j
            out = ctl.armour_control(dyn, gains, q, vd - (r - gains.Kr * e), qd, vd, ad, theta0, box)
            wn = np.linalg.norm(out.w_bar)
            excess_j = (out.lam - wn) * abs(out.err.r[joint]) / np.linalg.norm(out.err.r)  # what joint j sees of it
            vals = (abs(out.tau_nom[joint]), wn, excess_j, abs(out.v[joint]), abs(out.u[joint]))
            worst = np.maximum(worst, vals)
    return worst


def filtered_error(rng, kr, eps, steady=None):
    """A REACHABLE tracking error: e(t) of de/dt = r - Kr e, e(0) = 0, under piecewise-constant
    |r| = eps (random directions, or one held long)."""
    e = np.zeros(len(kr))
    pieces = (
        [(steady, 5.0)]
        if steady is not None
        else [(rng.normal(size=len(kr)), rng.uniform(0.02, 0.6)) for _ in range(6)]
    )
    for direction, h in pieces:
        decay = np.exp(-kr * h)
        e = decay * e + (1 - decay) * eps * direction / np.linalg.norm(direction) / kr
    return e


def margins(V_max: float, starts: int = 10, samples: int = 40) -> dict:
    from safesysid.benchmarks.bench_planner import Q0, near_boxes, table_ii_box
    from safesysid.systems.config import Planner
    from safesysid.systems.controller import armour as ctl
    from safesysid.systems.math.intervals import Interval
    from safesysid.systems.model.payload import load_dumbbells
    from safesysid.systems.model.robot_model import MODELS_DIR, load_robot
    from safesysid.systems.planner import interval_dynamics as idyn
    from safesysid.systems.planner import reachability as reach
    from safesysid.systems.planner import torque_certificate as tcert
    from safesysid.systems.planner.safe_planner import SafePlanner

    robot = load_robot(coulomb_smoothing=0.01)
    payload = load_dumbbells(MODELS_DIR / "dumbbells.yaml")["4lb"]
    theta0, lo, hi = table_ii_box(robot)
    box = Interval(lo, hi)
    gains = ctl.ArmourGains(np.array([5.0] * 4 + [7.0] * 3), 20.0, V_max)
    bounds = ctl.tracking_bounds_for(robot, gains, lo)
    dyn = ctl.ControllerDynamics(robot)
    limit = robot.joint_params.torque_limit
    rows = []
    for start in range(starts):
        rng = np.random.default_rng(100 + start)
        q = Q0 + rng.uniform(-0.3, 0.3, 7) * np.array([1, 0.5, 1, 0.5, 1, 0.5, 1])
        planner = SafePlanner(
            robot, Planner(), obstacles=near_boxes(robot, q, rng, payload=payload), payload=payload, tracking=bounds
        )
        prob = planner.problem(q, np.zeros(7), np.zeros(7), theta0, lo, hi)
        pr = prob.reach
        k_lo, k_hi, _ = pr.limit_box(robot.joint_params)
        f = 0.5**planner.torque_shrink_steps
        centre = np.clip(np.zeros(7), k_lo, k_hi)
        ks = (centre + f * (k_lo - centre), centre + f * (k_hi - centre))
        boxes = pr.state_boxes(*ks)
        wp = idyn.interval_passivity_regressor(robot, *boxes)
        excess = tcert.barrier_excess(robot, boxes[0], lo, hi, bounds)
        # before (interval boxes, the best of plain and aa-vertex w_bar) and now (the affine enclosure)
        sup_i, nom_i, robust_i = tcert.torque_bound(wp, theta0, lo, theta_hi=hi, excess=excess)
        wv, _ = tcert.robust_bound_vertex(robot, *boxes, theta0, lo, hi, robot.ee_slice, full=wp)
        sup_i = np.minimum(sup_i, nom_i + tcert.robust_term(wv, excess))
        states = pr.tube_states(*ks)
        wa = idyn.affine_passivity_regressor(robot, *states)
        sup, nominal, robust = tcert.affine_torque_bound(wa, theta0, lo, theta_hi=hi, excess=excess)
        wbar = robust - excess  # ||w_bar|| (+ rounding), the same for every joint
        i, j = np.unravel_index(np.argmax(sup / limit), sup.shape)
        t = rng.uniform(pr.edges[i], pr.edges[i + 1], samples // 8)
        desired = [
            np.concatenate(x)
            for x in zip(*(pr.bezier.evaluate(t[[c]], pr.q_end(rng.uniform(*ks))) for c in range(len(t))))
        ]
        s = sampled_command(robot, dyn, gains, desired, bounds, theta0, box, j, rng, 8)
        # Collision: certified spread of each sphere centre (planner's local_spread on the joint boxes of
        # the k box) vs sampled motion |c(q) - c(q_mid(k))|, q in the tube around q_d(t; k), t in I_i.
        kc, kh = 0.5 * (ks[0] + ks[1]), 0.5 * (ks[1] - ks[0])
        c_c, jac = reach.sphere_centres(robot.tree, planner.spheres, pr.q_mid(kc))
        k_dev = np.abs(pr.w_mid)[:, None] * (pr.kr * kh)[None, :]
        spread = reach.local_spread(
            robot.tree, planner.lipschitz, np.linalg.norm(jac, axis=-1), rho=pr.rho, reach_radius=pr.rho + k_dev
        )
        moved = 0.0
        for _ in range(200):
            kk = rng.uniform(*ks)
            tt = rng.uniform(pr.edges[i], pr.edges[i + 1])
            qq = pr.bezier.evaluate([tt], pr.q_end(kk))[0][0] + rng.choice([-1, 1], 7) * bounds.position
            cq, _ = reach.sphere_centres(
                robot.tree, planner.spheres, np.stack([qq, pr.q_mid(kk)[i]]), with_jacobian=False
            )
            moved = max(moved, float(np.linalg.norm(cq[0] - cq[1], axis=-1).max()))
        rows.append(
            {
                "start": start,
                "joint": int(j + 1),
                "t_s": float(pr.t_mid[i]),
                "limit_Nm": float(limit[j]),
                "certified": {
                    "total": float(sup[i, j]),
                    "nominal": float(nominal[i, j]),
                    "w_bar_norm": float(wbar[i, j]),
                    "excess": float(excess[i, j]),
                },
                "certified_interval_boxes": {
                    "total": float(sup_i[i, j]),
                    "nominal": float(nom_i[i, j]),
                    "w_bar_norm": float(np.minimum(robust_i, tcert.robust_term(wv, excess))[i, j] - excess[i, j]),
                },
                "sampled": {
                    "total": float(s[4]),
                    "nominal": float(s[0]),
                    "w_bar_norm": float(s[1]),
                    "excess": float(s[2]),
                    "v_j": float(s[3]),
                },
                "collision_spread_m": {
                    "certified_max": float(spread[i].max()),
                    "sampled_max": moved,
                },
                "k_box_half_width_after_limits": float(np.mean(k_hi - k_lo) / 2),
            }
        )
    keys = ("total", "nominal", "w_bar_norm", "excess")
    summary = {
        k: {
            "certified_median": float(np.median([r["certified"][k] for r in rows])),
            "sampled_median": float(np.median([r["sampled"][k] for r in rows])),
        }
        for k in keys
    }
    summary["sampled_total_over_limit"] = int(sum(r["sampled"]["total"] > r["limit_Nm"] for r in rows))
    summary["certified_total_over_limit"] = int(sum(r["certified"]["total"] > r["limit_Nm"] for r in rows))
    summary["interval_boxes_total_median"] = float(np.median([r["certified_interval_boxes"]["total"] for r in rows]))
    summary["interval_boxes_over_limit"] = int(
        sum(r["certified_interval_boxes"]["total"] > r["limit_Nm"] for r in rows)
    )
    return {"V_max": V_max, "eps": bounds.eps, "summary": summary, "starts": rows}


if __name__ == "__main__":
    values = [float(x) for x in sys.argv[1:]] or [0.02]
    print(json.dumps([margins(v) for v in values], indent=1))
