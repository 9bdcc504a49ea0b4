"""Which effects explain the gap: significance of a candidate on held-out residuals and the
forward-greedy selection.

it is significant, i.e. all of
  (1) held-out (validation) squared residual drops by more than Z_BLOCK standard errors of its
      random part (see `significance`; blocks of BLOCK_S seconds, so autocorrelated residuals
      do not fake significance), or the drop is consistent across blocks: a Wilcoxon
      signed-rank test of the per-block gains at the same 3-sigma level (P_BLOCKS). The first
      credits effects acting in bursts; the second effects that improve nearly every block
      while the residual left is heavy-tailed (real logs with unmodelled transients, whose
      few large blocks inflate the standard error),
  (2) the drop exceeds MIN_RELATIVE of the current validation mean square and MIN_NOISE_FRACTION
      of the noise variance (robust estimate from first differences of the validation residual):
      improvement beyond what measurement noise explains,
  (3) BIC on the inner training folds decreases,
  (4) relevance: on its most affected joint the effect changes the predicted torque by at
      least MIN_EFFECT_RATIO of the measured torque RMS (0.25 %, well below torque-sensor
      accuracy): a statistically clear but physically negligible mismatch, such as a
      simulator's own time discretisation, is not a cause.
A greedy addition past the best pair is the best of the K candidates left, so (1) holds there
at the family-wise level (family_levels): a larger library must not buy false positives.
An effect of the best pair that a rival lacks is not named (`unresolved`): the logs cannot tell
which of the two sets acts, so only what the best set and every rival share is a finding. A
rival is an admissible set of no more effects than the best whose validation residual is within
Z_NAME = 1 standard error of the best's (the one-standard-error rule; `ambiguous` reports the
wider Z_AMBIGUOUS band) and whose effects the greedy additions do not name anyway.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .cross_validation import CrossValidated
from .design import rms
from .effects import PER_JOINT, TIME_LAWS, Params
from .problem import FoldParams, Problem, n_params

Evaluator = Problem | CrossValidated  # selects on check logs / on inner-fold validation residuals

Z_BLOCK = 3.0
P_BLOCKS = 0.00135  # one-sided p of the block signed-rank test: the same 3-sigma level as Z_BLOCK
MIN_BLOCKS = 12  # fewer blocks cannot reach P_BLOCKS reliably: the rank test then abstains
MIN_RELATIVE = 0.01
MIN_NOISE_FRACTION = 0.05
MIN_EFFECT_RATIO = 0.0025  # effect RMS / measured torque RMS on its most affected joint
# The greedy step picks the best of K candidates, each passing (1) by either of two tests: its
# z and rank-test p are held to P_BLOCKS / (2 K) (Bonferroni over both tests and the K tried).
FAMILY_TESTS = 2
Z_AMBIGUOUS = 2.0  # two admissible sets whose held-out difference is under 2 standard errors: ambiguous
Z_NAME = 1.0  # a rival within 1 standard error of the best set: their differing effects are not named
# What excites each effect (and not the others): the data that would tell two effect sets apart.
EXCITED_BY = {
    "coulomb_friction": "velocity reversals and slow constant-speed motion",
    "viscous_friction": "a wide range of constant speeds",
    "stribeck_friction": "slow motion through and near zero speed",
    "load_friction": "large transmitted torques at speed, in both directions",
    "armature": "high accelerations",
    "torque_offset": "poses that change the sign of the gravity torque",
    "torque_scale": "large torques of both signs",
    "payload": "wrist poses and accelerations that change the end effector's gravity and inertia",
    "time_delay": "fast torque changes (high-frequency motion)",
    "base_tilt": "first-joint rotations at stretched poses (the gravity direction in the base)",
    "joint_elasticity": "large load changes at poses where gravity depends on the joint angles",
}


def noise_variance(r: np.ndarray, block: np.ndarray, joint: np.ndarray) -> float:
    """White-noise variance from first differences in time inside blocks, per joint (smooth
    effects cancel), robust to sharp bursts (median absolute difference)."""
    out = []
    for j in np.unique(joint):
        m = joint == j
        d = np.diff(r[m])[block[m][1:] == block[m][:-1]]
        if len(d):
            out.append((1.4826 * np.median(np.abs(d))) ** 2 / 2)
    return float(np.mean(out)) if out else float(np.mean(r**2))


def resolvable(problem: Evaluator, params: Params | FoldParams) -> bool:
    """A delay shorter than half the logs' sample period is below what the logs resolve (and
    of the order of a simulator's own step): never reported as a cause (in any inner fold)."""
    if isinstance(params, tuple):
        return all(resolvable(problem, p) for p in params)
    d = _delay_of(params)
    return d is None or abs(d) >= problem.min_delay


def _delay_of(params):
    for g in TIME_LAWS:
        if g in params:
            return float(params[g][0])
    if "time_delay" in params:
        return float(params["time_delay"][0])
    return None


def family_levels(k: int) -> tuple[float, float]:
    """(z, p) thresholds of rule (1) for the best of k candidates tried at once: each at
    P_BLOCKS / (FAMILY_TESTS k), so the chance that any of them passes on noise stays at
    about P_BLOCKS; k = 0 is a single pre-planned test (Z_BLOCK, P_BLOCKS)."""
    from scipy.stats import norm

    if k <= 0:
        return Z_BLOCK, P_BLOCKS
    p = P_BLOCKS / (FAMILY_TESTS * k)
    return float(norm.isf(p)), p


def significance(
    problem: Evaluator,
    r0: np.ndarray,
    r1: np.ndarray,
    sse0_fit: float,
    sse1_fit: float,
    k_added: int,
    *,
    joint: int | None = None,
    family: int = 0,
) -> dict:
    """The significance rule of the module docstring. r0/r1: held-out residual vectors of
    `problem` (validation residuals of the inner folds in the honest protocol).

    With c = r0 - r1 (the candidate's change of prediction), the held-out gain is
    sum(r0^2 - r1^2) = sum(2 r1 c + c^2); only 2 r1 c is random (r1 estimates the noise), so its
    standard error is taken from block sums of 2 r1 c (blocks absorb autocorrelation) and
    z = gain / se. Effects acting in short bursts (Stribeck at reversals) are then judged by
    how far each burst stands out of the noise, not by how many bursts a log happens to have.
    family: the number of candidates this one is the best of (family_levels; 0: one test)."""
    sel = slice(None) if joint is None else (problem.check_joint == joint)
    r0, r1 = r0[sel], r1[sel]
    blocks = problem.check_block[sel]
    joints = problem.check_joint[sel]
    mse0 = float(np.mean(r0**2))
    gain = r0**2 - r1**2
    delta = float(np.mean(gain))
    cross = np.bincount(blocks, weights=2 * r1 * (r0 - r1))
    se = float(np.sqrt(np.sum(cross**2)))
    total = float(np.sum(gain))
    z = total / se if se > 0 else (np.inf if total > 1e-12 * max(np.sum(r0**2), 1e-300) else 0.0)
    p_blocks = _signed_rank_p(np.bincount(blocks, weights=gain)[np.bincount(blocks) > 0])
    sigma2 = noise_variance(r0, blocks, joints)
    change = r0 - r1
    relevance = max(
        float(np.sqrt(np.mean(change[joints == j] ** 2)) / max(problem.tau_rms_check[j], 1e-12))
        for j in np.unique(joints)
    )
    m = problem.n_fit_rows
    bic = m * np.log(max(sse1_fit, 1e-300) / max(sse0_fit, 1e-300)) + k_added * np.log(m)
    z_crit, p_crit = family_levels(family)
    ok = bool(
        (z >= z_crit or p_blocks <= p_crit)
        and delta >= MIN_RELATIVE * mse0
        and delta >= MIN_NOISE_FRACTION * sigma2
        and relevance >= MIN_EFFECT_RATIO
        and (joint is not None or bic < 0)
    )
    return {
        "significant": ok,
        "z": float(z),
        "p_blocks": p_blocks,
        "delta_mse": delta,
        "relative": delta / mse0 if mse0 > 0 else 0.0,
        "noise_variance": sigma2,
        "bic_change": float(bic),
        "relevance": relevance,
    }


def _signed_rank_p(block_gain):
    """One-sided p of the Wilcoxon signed-rank test that block gains are positive (1 when there
    are fewer than MIN_BLOCKS blocks or no nonzero gain)."""
    from scipy.stats import wilcoxon

    g = block_gain[block_gain != 0]
    if len(block_gain) < MIN_BLOCKS or len(g) == 0:
        return 1.0
    return float(wilcoxon(g, alternative="greater").pvalue)


@dataclass
class Selection:
    effects: list[str]  # selected, most important first
    params: Params | FoldParams  # evaluator parameters of the selected set
    residual: np.ndarray  # evaluator residual (valid elements) after the selected set
    steps: list[dict]
    single: dict[str, dict]  # effect -> {params, sse, r, sig}: each effect alone
    joints: dict[str, list[int]]  # selected effect -> 1-based joints where it matters
    ambiguous: list[dict] = field(default_factory=list)  # other sets explaining the validation data as well
    unresolved: list[str] = field(default_factory=list)  # best-pair effects an equally good set lacks: not named


def _drop(params, effect):
    """params without the groups of `effect` (per fold for inner folds)."""
    if isinstance(params, tuple):
        return tuple(_drop(p, effect) for p in params)
    return {g: v for g, v in params.items() if g.split("@")[0] != effect}


def select_effects(ev: Evaluator, effects: Sequence[str], max_effects: int) -> Selection:
    """The selection of the module docstring on an evaluator `ev` (CrossValidated: validation
    residuals of inner folds of the fit logs; a Problem would select on its check logs)."""
    n = ev.n
    r0, sse0 = ev.y_check, ev.yy
    single = {}
    for e in effects:
        params, sse = ev.fit_effects([e])
        r1 = ev.check_residual(params)
        sig = significance(ev, r0, r1, sse0, sse, n_params(params))
        sig["significant"] &= resolvable(ev, params)
        single[e] = {"params": params, "sse": sse, "r": r1, "sig": sig}
    # The best pair (or single) first, exhaustively, then forward-greedy.
    selected, cur_params, cur_sse, cur_r, steps, ambiguous = _best_small_set(ev, effects, single, r0, sse0)
    while len(selected) < max_effects:
        best = None
        left = [e for e in effects if e not in selected]
        for e in left:
            params, sse = ev.fit_effects(selected + [e])
            r1 = ev.check_residual(params)
            k_added = n_params(params) - n_params(cur_params)
            sig = significance(ev, cur_r, r1, cur_sse, sse, k_added, family=len(left))
            sig["significant"] &= resolvable(ev, params)
            if sig["significant"] and (best is None or sig["delta_mse"] > best[4]["delta_mse"]):
                best = (e, params, sse, r1, sig)
        if best is None:
            break
        e, cur_params, cur_sse, cur_r, sig = best
        selected.append(e)
        steps.append({"effect": e, "rms_after": rms(cur_r), **sig})
    unresolved = contested([s["effect"] for s in steps if s.get("phase") == "best pair"], ambiguous, selected)
    if unresolved:  # name only what every equally good set shares
        selected = [e for e in selected if e not in unresolved]
        cur_params, _ = ev.fit_effects(selected)
        cur_r = ev.check_residual(cur_params)
    # Most important first: the validation loss when an effect is left out of the final set.
    if len(selected) > 1:
        loss = {}
        for e in selected:
            params, _ = ev.fit_effects([x for x in selected if x != e])
            loss[e] = float(np.mean(ev.check_residual(params) ** 2) - np.mean(cur_r**2))
        selected.sort(key=lambda e: -loss[e])
    # Joints where each selected effect matters: removing it from the combined fit on that
    # joint must lose a significant amount on the validation residuals.
    joints = {}
    for e in selected:
        r_wo = ev.check_residual(_drop(cur_params, e))
        if e in PER_JOINT:
            js = [j + 1 for j in range(n) if significance(ev, r_wo, cur_r, 1, 1, 0, joint=j)["significant"]]
        else:
            gain = np.array(
                [np.mean(r_wo[ev.check_joint == j] ** 2 - cur_r[ev.check_joint == j] ** 2) for j in range(n)]
            )
            js = [j + 1 for j in range(n) if gain[j] > MIN_RELATIVE * np.mean(r_wo[ev.check_joint == j] ** 2)]
        joints[e] = js or list(range(1, n + 1))
    return Selection(selected, cur_params, cur_r, steps, single, joints, ambiguous, unresolved)


def contested(best: Sequence[str], ambiguous: Sequence[dict], selected: Sequence[str] = ()) -> list[str]:
    """The effects of the best set that a rival lacks. Rivals: the equally good sets (equally_good)
    within Z_NAME standard errors, of no more effects than `best` (a larger set explaining the data
    as well is the less parsimonious explanation), not wholly in the selection (`selected`: the
    best set and the greedy additions past it)."""
    rivals = [
        a["effects"]
        for a in ambiguous
        if a["difference_z"] < Z_NAME and len(a["effects"]) <= len(best) and not set(a["effects"]) <= set(selected)
    ]
    return [e for e in best if any(e not in r for r in rivals)]


def _best_small_set(ev, effects, single, r0, sse0_fit):
    """Exhaustive search over sets of one or two effects (greedy alone can pick one effect
    that mimics two, e.g. a torque scale for armature + delay on an arm with large nominal
    armature, or miss two effects that only fit together, e.g. payload + base tilt, both
    gravity-like). A set is admissible when each member is significant against the set without
    it; the admissible set with the lowest validation residual wins."""
    fits = {(): (ev.empty, sse0_fit, r0)}
    for e in effects:
        fits[(e,)] = (single[e]["params"], single[e]["sse"], single[e]["r"])
    admissible = [()] + [(e,) for e in effects if single[e]["sig"]["significant"]]
    for i, e in enumerate(effects):
        for f in effects[i + 1 :]:
            params, sse = ev.fit_effects([e, f])
            r = ev.check_residual(params)
            fits[(e, f)] = (params, sse, r)
            ok = resolvable(ev, params)
            for keep in (e, f):
                p0, s0, rr0 = fits[(keep,)]
                ok = ok and significance(ev, rr0, r, s0, sse, n_params(params) - n_params(p0))["significant"]
            if ok:
                admissible.append((e, f))
    best = min(admissible, key=lambda k: float(np.mean(fits[k][2] ** 2)))
    ambiguous = equally_good(ev, best, {k: fits[k][2] for k in admissible})
    params, sse, r = fits[best]
    steps = []
    prev = ()
    order = sorted(best, key=lambda e: float(np.mean(fits[(e,)][2] ** 2)))
    for e in order:
        cur = tuple(sorted((x for x in best if x in prev + (e,)), key=best.index))
        p1, s1, r1 = fits[cur]
        p0, s0, rr0 = fits[prev]
        sig = significance(ev, rr0, r1, s0, s1, n_params(p1) - n_params(p0))
        steps.append({"effect": e, "rms_after": rms(r1), "phase": "best pair", **sig})
        prev = cur
    return list(order), params, sse, r, steps, ambiguous


def difference_z(ev: Evaluator, r_a: np.ndarray, r_b: np.ndarray) -> float:
    """Held-out difference of two sets' squared residuals in standard errors of its block sums
    (positive: b explains the validation data better than a)."""
    diff = np.bincount(ev.check_block, weights=r_a**2 - r_b**2)
    se = float(np.sqrt(np.sum((diff - diff.mean()) ** 2) * len(diff) / max(len(diff) - 1, 1)))
    return float(diff.sum() / se) if se > 0 else 0.0


def equally_good(ev: Evaluator, best: tuple, residuals: dict[tuple, np.ndarray]) -> list[dict]:
    """Admissible sets other than `best` (not a subset of it) whose validation residual is within
    Z_AMBIGUOUS standard errors of best's: each with its score and the data that would separate it
    from best (what excites the effects the two sets do not share)."""
    out = []
    for other, r in residuals.items():
        if not other or set(other) <= set(best):
            continue
        z = difference_z(ev, r, residuals[best])
        if z < Z_AMBIGUOUS:
            only_best = [e for e in best if e not in other]
            only_other = [e for e in other if e not in best]
            out.append(
                {
                    "effects": list(other),
                    "rms_validation": rms(r),
                    "rms_validation_best": rms(residuals[best]),
                    "difference_z": z,
                    "separating_data": "; ".join(f"{e}: {EXCITED_BY[e]}" for e in only_best + only_other),
                }
            )
    return sorted(out, key=lambda x: x["rms_validation"])
