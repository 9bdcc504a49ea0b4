"""Table IV and Fig. 5 from a compare of ours and random (app/table_iv.py): the numbers against
hand-computed ones on made-up summaries, and a tiny compare end to end; the default estimator
bounds all ten parameters (the paper's Fig. 5)."""

import csv
import dataclasses
import json

import numpy as np
from helpers import CENTRE, PRIOR, PRIOR_NOMINAL
from safesysid.cli import main
from safesysid.scenario import SCENARIOS_DIR, load_scenario
from safesysid.systems import estimation as E
from safesysid.systems.model.payload import payload_theta_in_end_effector
from safesysid.table_iv import PAPER_COND_Y, table_iv, write_identification_results


def summary(method, dumbbell, trial, cond_y, widths):
    half = np.asarray(widths, float) / 2
    return {
        "method": method,
        "dumbbell": dumbbell,
        "trial": trial,
        "cond_Y": cond_y,
        "payload_true": {"theta": [2.0] + [0.0] * 9},
        "estimate": {"nominal": [2.0] + [0.0] * 9, "lower": (-half).tolist(), "upper": half.tolist()},
    }


def made_up_runs():
    """4lb: two trials; ours narrower on every parameter but the last in trial 0, on none in trial 1
    (ratio 2). 5lb: one trial, ours' cond(Y) higher."""
    ones = np.ones(10)
    return [
        summary("ours", "4lb", 0, 100.0, np.r_[0.5 * ones[:9], 1.0]),
        summary("random", "4lb", 0, 300.0, ones),
        summary("ours", "4lb", 1, 200.0, 2 * ones),
        summary("random", "4lb", 1, 250.0, ones),
        summary("ours", "5lb", 0, 500.0, 0.25 * ones),
        summary("random", "5lb", 0, 400.0, ones),
        summary("wrong", "5lb", 0, 1.0, ones),  # not part of Table IV
    ]


def test_table_iv_spreads_pairs_and_width_ratios_on_made_up_runs():
    doc = table_iv([s for s in made_up_runs() if s["method"] != "wrong"], ["4lb", "5lb"])
    four = doc["dumbbells"]["4lb"]
    assert (four["ours"]["median"], four["ours"]["min"], four["ours"]["max"]) == (150.0, 100.0, 200.0)
    assert four["random"]["median"] == 275.0 and four["ours_lower"] == 2 and four["pairs"] == 2
    assert four["paper"] == {"ours": PAPER_COND_Y["4lb"][0], "random": PAPER_COND_Y["4lb"][1]}
    assert doc["dumbbells"]["5lb"]["ours_lower"] == 0
    # per parameter over the three pairs: ratios (0.5, 2, 0.25) -> median 0.5, won 2/3; the last (1, 2, 0.25)
    r = doc["width_ratio"]
    assert r["pairs"] == 3 and r["parameters_below_1"] == 9
    assert np.allclose(r["median"], [0.5] * 9 + [1.0]) and np.allclose(r["won"], [2 / 3] * 9 + [1 / 3])
    assert np.allclose(four["width_ratio"]["median"], [1.25] * 9 + [1.5])


def test_writer_files_name_every_dumbbell(tmp_path):
    written = write_identification_results(tmp_path, "made_up", made_up_runs(), dumbbells=["4lb", "5lb"], prior=PRIOR)
    assert {p.name for p in written} == {"table_iv.md", "table_iv.csv", "table_iv.json", "fig5_4lb.png", "fig5_5lb.png"}
    with (tmp_path / "table_iv.csv").open() as fh:
        rows = list(csv.reader(fh))
    assert rows[1][:4] == ["4lb", "150 [100-200]", "275 [250-300]", "2/2"] and rows[2][3] == "0/1"
    assert "| median ratio | 0.500 |" in (tmp_path / "table_iv.md").read_text()
    assert write_identification_results(tmp_path, "x", made_up_runs()[:1], dumbbells=["4lb"], prior=PRIOR) == []


def test_tiny_compare_of_ours_and_random_writes_table_iv_and_fig5(tmp_path):
    out = tmp_path / "cmp"
    args = ["compare", str(SCENARIOS_DIR / "quickstart.yaml"), "--methods", "ours,random", "--dumbbells", "4lb"]
    short = "planner: {num_plans: 1, duration_s: 1.0, replan_period_s: 0.5}"
    assert main([*args, "--trials", "1", "--workers", "2", "--out", str(out), "--scenario-text", short]) == 0
    runs = {s["method"]: s for s in map(json.loads, (out / "runs.jsonl").read_text().splitlines())}
    doc = json.loads((out / "table_iv.json").read_text())
    for method in ("ours", "random"):
        assert doc["dumbbells"]["4lb"][method]["values"] == [runs[method]["cond_Y"]]
    widths = {m: np.subtract(s["estimate"]["upper"], s["estimate"]["lower"]) for m, s in runs.items()}
    assert np.allclose(doc["width_ratio"]["median"], widths["ours"] / widths["random"])
    assert (out / "fig5_4lb.png").stat().st_size > 5000


def test_the_default_estimator_bounds_all_ten_parameters(robot, dumbbells):
    """estimator.set_membership defaults to all: on the same 3 s log every interval lies inside the
    mass-only LP's and the first moments come out narrower (with mass they keep the Theorem 2 box)."""
    settings = E.EstimatorSettings.from_scenario(load_scenario(SCENARIOS_DIR / "quickstart.yaml"))
    rng = np.random.default_rng(3)
    theta = E.perturbed_robot_theta(rng, robot, 0.05)
    theta[robot.ee_slice] = robot.theta_e + payload_theta_in_end_effector(dumbbells["4lb"], robot.extra["grasp_point"])
    log = E.simulate_log(rng, robot, theta, duration_s=3.0, rate_hz=1000.0, centre=CENTRE)[:4]
    boxes = {}
    for mode in ("mass", settings.set_membership):
        est = E.IncrementalEstimator(
            robot, settings=dataclasses.replace(settings, set_membership=mode), prior=PRIOR, prior_nominal=PRIOR_NOMINAL
        )
        est.add(*log)
        boxes[mode] = est.update()
    default, mass = boxes[settings.set_membership], boxes["mass"]
    assert np.all(default.lower >= mass.lower - 1e-12) and np.all(default.upper <= mass.upper + 1e-12)
    assert np.all(default.widths[1:4] < 0.9 * mass.widths[1:4]), (default.widths, mass.widths)
