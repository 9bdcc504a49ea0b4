"""scenarios/identify_all.yaml over paired seeds (issue 15), SAFESYSID_FULL=1 only (40 closed-loop
runs, ~17 min on one core of this 2-core machine):

    SAFESYSID_FULL=1 python -m pytest -q tests/test_estimator_identify_all.py

Payloads 4-8 lb, robot parameters drawn in their box (the scenario's plant.robot_parameters: drawn),
torque noise uniform inside the declared bound; ours and random with the same seeds. CI checks the
same estimator paths on synthetic logs (tests/test_estimator_prior.py, test_estimator_physical.py).
"""

import dataclasses

import numpy as np
import pytest
from helpers import FULL, PAYLOADS, PRIOR
from safesysid.online import run_online
from safesysid.scenario import SCENARIOS_DIR, load_scenario

pytestmark = pytest.mark.skipif(not FULL, reason="20 paired closed-loop seeds: SAFESYSID_FULL=1")
SEEDS = range(20)
WIDTH_PRIOR = PRIOR[1] - PRIOR[0]


@pytest.fixture(scope="module")
def runs():
    base = load_scenario(SCENARIOS_DIR / "identify_all.yaml")
    out = {}
    for seed in SEEDS:
        scene = dataclasses.replace(
            base, payload=dataclasses.replace(base.payload, dumbbell=PAYLOADS[seed % len(PAYLOADS)])
        )
        for method in ("ours", "random"):
            out[method, seed] = run_online(scene, None, method=method, seed=seed, write=False)
    return out


def widths(summary, key=""):
    e = summary["estimate"]
    return np.array(e[f"{key}upper"]) - np.array(e[f"{key}lower"])


def test_truth_inside_every_published_interval(runs):
    assert all(s["contains_truth"] and s["estimate"]["consistent"] for s in runs.values())
    for s in runs.values():
        truth, e = np.array(s["payload_true"]["theta"]), s["estimate"]
        assert np.all((np.array(e["data_lower"]) <= truth) & (truth <= np.array(e["data_upper"])))


def test_every_interval_narrower_than_the_prior_and_inertias_within_half_of_it(runs):
    for (method, seed), s in runs.items():
        ratio = widths(s) / WIDTH_PRIOR
        assert np.all(ratio < 1.0), (method, seed, ratio)
        assert np.all(ratio[4:] <= 0.5), (method, seed, ratio)


@pytest.mark.xfail(
    strict=True,
    reason="out of reach with the robot-parameter box: the LP with the +-5 % robot box alone (no torque "
    "noise) leaves a mass half-width of 0.104-0.122 kg (benchmarks/interval_budget.py)",
)
def test_mass_half_width_at_most_a_tenth_of_a_kilogram(runs):
    assert max(widths(s)[0] / 2 for s in runs.values()) <= 0.1


def test_the_data_alone_narrow_every_inertia_below_the_prior(runs):
    """Ours' data-driven box (before the bounding-volume pruning): each of the six inertias
    narrower than the prior (point-certified plans; with the k box alone they stayed at it)."""
    for seed in SEEDS:
        ratio = widths(runs["ours", seed], "data_") / WIDTH_PRIOR
        assert np.all(ratio < 1.0), (seed, ratio)


@pytest.mark.xfail(
    strict=True,
    reason="measured 12/20 pairs (wave 2, sessions 6-13; README lists the variants tried, the best 13/20): ours "
    "narrower than random on 14, 10, 11, 19, 16, 19, 13, 15, 16, 17 of 20 pairs per parameter; the mass's width "
    "does not move with the motion (a coin flip), m cx and m cy trade against each other, and Izz is seen mostly "
    "through joints 1-6",
)
def test_ours_narrower_than_random_on_eight_of_ten_parameters_in_most_pairs(runs):
    """The paper's Fig. 5 claim on the data-driven intervals: >= 8 of 10 in >= 80 % of the pairs."""
    wins = [int(np.sum(widths(runs["ours", s], "data_") < widths(runs["random", s], "data_"))) for s in SEEDS]
    print("parameters where ours is narrower, per pair:", wins)
    assert sum(w >= 8 for w in wins) >= 0.8 * len(SEEDS)


def test_exciting_plans_condition_the_data_better_than_random(runs):
    """The paper's Table IV claim on this scene: median cond(Y) ours / random <= 0.7 (paired seeds)."""
    cond = {m: np.array([runs[m, seed]["cond_Y"] for seed in SEEDS]) for m in ("ours", "random")}
    ratio = np.median(cond["ours"]) / np.median(cond["random"])
    lower = int(np.sum(cond["ours"] < cond["random"]))
    print(f"median cond(Y) ours {np.median(cond['ours']):.0f} / random {np.median(cond['random']):.0f} = {ratio:.2f}")
    print(f"ours lower in {lower}/{len(SEEDS)} pairs")
    assert ratio <= 0.7
