"""Diagnosed values with statistical intervals (systems/diagnosis/intervals.py), the ambiguity
report (selection.equally_good) and the self-check's hard mode."""

import numpy as np
import pytest
import yaml
from safesysid.systems import diagnosis as dg
from safesysid.systems.diagnosis import intervals as iv
from safesysid.systems.model.joint_data import JointLog
from safesysid.systems.model.robot_model import load_robot
from test_gap import TWO_LINK


@pytest.fixture(scope="module")
def two_link(tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "two_link.urdf"
    path.write_text(TWO_LINK)
    return load_robot(model_path=path)


def _regression(rng, rows=2000, block=50, rho=0.8):
    """Linear data with AR(1) noise (correlated inside blocks of `block` rows)."""
    X = rng.normal(size=(rows, 3)).cumsum(0) / 10 + rng.normal(size=(rows, 3))
    e = np.zeros(rows)
    for k in range(1, rows):
        e[k] = rho * e[k - 1] + rng.normal()
    p_true = np.array([1.0, -2.0, 0.5])
    y = X @ p_true + e
    p = np.linalg.lstsq(X, y, rcond=None)[0]
    return X, y - X @ p, np.arange(rows) // block, p, p_true


def test_block_sandwich_intervals_cover_under_autocorrelated_noise():
    """90 % block-sandwich intervals hold the true parameter in about 90 % of replications of a
    regression with autocorrelated noise and smooth regressors (about 86 %: neighbouring blocks
    are not quite independent; an i.i.d. formula gives about 50 %), and the block bootstrap agrees
    with the sandwich's width."""
    rng = np.random.default_rng(0)
    hits, ratios = [], []
    for rep in range(200):
        X, r, block, p, p_true = _regression(rng)
        cov, ok = iv.sandwich_covariance(X, r, block)
        n_blocks = block.max() + 1
        half = iv.student_t.ppf(0.95, n_blocks - 1) * np.sqrt(np.diag(cov))
        hits.append(np.abs(p - p_true) <= half)
        if rep % 20 == 0:
            draws = iv.block_bootstrap(X, r, block, rng, draws=300)
            boot = 0.5 * (np.quantile(draws, 0.95, 0) - np.quantile(draws, 0.05, 0))
            ratios.append(np.median(boot / (1.6449 * np.sqrt(np.diag(cov)))))
    coverage = float(np.mean(hits))
    assert 0.83 <= coverage <= 0.95, coverage
    assert 0.8 <= np.median(ratios) <= 1.25, ratios


def _logs(model, seed, effects, *, amplitude=None, noise=0.3, n=3):
    rng = np.random.default_rng(seed)
    logs = []
    for _ in range(n):
        if amplitude is None:
            traj = dg.random_trajectory(model, rng)
        else:  # small motion about one pose: the gravity torque hardly changes
            traj = dg.Trajectory(
                np.array([0.6, -0.4]),
                amplitude * rng.uniform(0.5, 1, (3, 2)),
                2 * np.pi * rng.uniform(0.2, 0.7, (3, 2)),
                rng.uniform(0, 2 * np.pi, (3, 2)),
            )
        t = dg.sample_times(rng, 10.0)
        q, v, _, tau = dg.true_torque(model, traj, t, effects=effects)
        logs.append(JointLog(t, q, v, tau + noise * rng.uniform(-1, 1, tau.shape), None, {}, "sim"))
    return logs


def test_diagnosed_values_carry_intervals_into_the_corrected_model(two_link, tmp_path):
    """Each named effect's values get 90 % statistical intervals holding the injected values; the
    corrected_model.yaml carries them (time_delay under delay_s) and reads them back; a malformed
    interval is named by file and field."""
    effects = {"viscous_friction": {"delta": np.array([1.5, 0.0])}, "time_delay": {"delay_s": 0.03, "law": "lag"}}
    logs = _logs(two_link, 4, effects)
    d = dg.diagnose(two_link, logs[:2], logs[2:], effects=("viscous_friction", "torque_offset", "time_delay"))
    assert sorted(d.result["cause"]) == ["time_delay", "viscous_friction"]
    by = {e["name"]: e for e in d.result["effects"]}
    lo, hi = by["time_delay"]["intervals"]["delay_s"]
    assert lo <= 0.03 <= hi and hi - lo < 0.02
    (lo_v, hi_v) = by["viscous_friction"]["intervals"]["delta_Fv_Nms_rad"]
    assert lo_v[0] <= 1.5 <= hi_v[0]
    assert "not Algorithm 1" in d.result["intervals_note"]
    path = dg.write_corrected_model(tmp_path / "corrected_model.yaml", d.corrected_model)
    back = dg.read_corrected_model(path)
    assert {e.name: e.intervals for e in back.effects}["time_delay"]["delay_s"] == [lo, hi]
    doc = yaml.safe_load(path.read_text())
    doc["effects"][0]["intervals"] = {"delay_s": [0.1]}
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(dg.CorrectedModelError, match=r"corrected_model.yaml: effects\[0\].intervals.delay_s: "):
        dg.read_corrected_model(path)


def test_sets_that_explain_the_logs_equally_well_are_reported_ambiguous(two_link):
    """A payload moved only a little about one pose (its gravity torque nearly constant) is
    explained nearly as well by torque offsets: diagnosis.json says `ambiguous`, with both sets,
    their scores and the data that would separate them (the payload is still named: its lead is
    beyond Z_NAME); the same payload on wide motions is not ambiguous."""
    payload = {"payload": {"theta": dg.payload_theta(two_link, 0.5, np.random.default_rng(1))}}
    candidates = ("payload", "torque_offset", "viscous_friction")
    logs = _logs(two_link, 3, payload, amplitude=0.01, noise=0.05)
    d = dg.diagnose(two_link, logs[:2], logs[2:], effects=candidates)
    amb = d.result["ambiguous"]
    assert d.result["cause"] == ["payload"] and d.result["unresolved"] == []
    pairs = [{tuple(s["effects"]) for s in a["sets"]} for a in amb]
    assert {("payload",), ("torque_offset",)} in pairs, amb
    a = amb[[("torque_offset",) in p for p in pairs].index(True)]
    assert abs(a["difference_z"]) < dg.Z_AMBIGUOUS and all(s["rms_check"] > 0 for s in a["sets"])
    assert "gravity torque" in a["separating_data"]
    logs = _logs(two_link, 3, payload, noise=0.05)
    wide = dg.diagnose(two_link, logs[:2], logs[2:], effects=candidates).result
    assert wide["cause"] == ["payload"] and wide["ambiguous"] == [] and wide["unresolved"] == []


def test_a_rival_within_one_standard_error_leaves_the_contested_effect_unnamed(two_link):
    """A payload moved 0.003 rad about one pose: torque offsets explain the validation data within
    a fraction of a standard error. Neither is named; the best set's payload is `unresolved`,
    absent from the corrected model, and `ambiguous` lists both sets; report.md says so."""
    from safesysid.diagnose_report import verdict_lines

    payload = {"payload": {"theta": dg.payload_theta(two_link, 0.5, np.random.default_rng(1))}}
    logs = _logs(two_link, 4, payload, amplitude=0.003, noise=0.05)
    d = dg.diagnose(two_link, logs[:2], logs[2:], effects=("payload", "torque_offset", "viscous_friction"))
    (amb,) = d.result["ambiguous"]
    assert [s["effects"] for s in amb["sets"]] == [["payload"], ["torque_offset"]]
    assert amb["difference_z"] < dg.selection.Z_NAME
    assert d.result["cause"] == [] and d.result["unresolved"] == ["payload"] and d.corrected_model.effects == []
    why = verdict_lines(d.result)[1]
    assert why.startswith(
        "**Why:** no effect is named. **Not named:** payload: torque_offset explains the fit logs as well"
    ), why
    assert "gravity torque" in why


def test_only_effects_every_equally_good_set_shares_are_named():
    """The best set's effects that a rival lacks are contested (not named); an effect every rival
    shares is kept. Not rivals: a set further than Z_NAME standard errors (still `ambiguous`), a
    larger set, and a set the selection holds too (greedy additions past the best pair)."""
    from safesysid.systems.diagnosis.selection import Z_NAME, contested

    best = ["viscous_friction", "armature"]
    rival = lambda effects, z=0.5: {"effects": effects, "difference_z": z}  # noqa: E731
    assert contested(best, []) == []
    assert contested(best, [rival(["viscous_friction", "torque_scale"])]) == ["armature"]
    both = [rival(["viscous_friction", "torque_scale"]), rival(["armature", "torque_scale"])]
    assert contested(best, both) == best
    assert contested(best, [rival(["torque_scale"], Z_NAME + 0.1)]) == []
    assert contested(["armature"], [rival(["viscous_friction", "torque_scale"])]) == []
    assert contested(best, both[:1], [*best, "torque_scale"]) == []


def test_hard_plan_is_two_effects_at_full_noise_without_accelerations():
    plan = dg.case_plan(200, np.random.default_rng(0), hard=True)
    nulls = [p for p in plan if not p["injected"]]
    assert len(nulls) == 40 and all(len(p["injected"]) == 2 for p in plan if p["injected"])
    assert all(not p["with_acceleration"] and p["noise_level"] == 0.03 for p in plan)
    assert 70 <= sum(p["same_joints"] for p in plan) <= 90


def test_residual_map_shows_where_the_residual_left_lies(two_link, tmp_path):
    """Stribeck friction on joint 2 left uncorrected (not a candidate): the residual map puts the
    residual on joint 2, concentrated near zero velocity and at reversals, and draws it."""
    from safesysid.diagnose_plots import write_plots

    effects = {"stribeck_friction": {"delta": np.array([0.0, 2.0]), "vs": 0.05}}
    logs = _logs(two_link, 5, effects, noise=0.05)
    d = dg.diagnose(two_link, logs[:2], logs[2:], effects=("torque_offset",))
    joints = d.result["combined"]["residual_map_after"]["joints"]
    assert joints[1]["share"] > 0.9
    ratio = {k: c["share"] / c["samples"] for k, c in joints[1]["regimes"].items() if c["samples"] > 0}
    assert ratio["near_zero_velocity"] > 2 and ratio["reversal"] > 2 and ratio["high_speed"] < 0.5
    assert sum(b["samples"] for b in joints[1]["pose_bins"]) == pytest.approx(1.0)
    assert (tmp_path / write_plots(tmp_path, d)["residual_map"]).is_file()


def test_interval_factors_are_chosen_on_even_cases_and_scored_on_odd_ones():
    """calibrated_coverage: each effect's factor is the 90th percentile of the widening its values
    needed on the even cases; the odd cases are scored with it. spurious_table counts false names
    per null / non-null case and per effect in the cases that lack it."""

    def case(k, fitted):  # truth 1.0, interval fitted +- 0.05: 0.9 needs 2x widening, 0.95 none
        rec = {"effect": "time_delay", "key": "delay_s", "index": None, "truth": 1.0}
        return {
            "case": k,
            "injected": ["time_delay"],
            "false": ["armature"] if k == 3 else [],
            "fitted": {"time_delay": {"delay_s": fitted}},
            "coverage": [{**rec, "lo": fitted - 0.05, "hi": fitted + 0.05}],
        }

    cases = [case(k, 0.95 if k % 4 == 0 else 0.9) for k in range(40)]
    cov = dg.truth_scores.calibrated_coverage(cases)
    assert cov["factors"]["time_delay"] == pytest.approx(2.0)
    assert cov["held_out_values"] == 20 and cov["held_out_rate"] == 1.0
    sp = dg.truth_scores.spurious_table(cases + [{"injected": [], "false": []}])
    assert sp["non_null_with_false_effect"] == pytest.approx(1 / 40) and sp["null_with_false_effect"] == 0
    assert sp["per_effect"]["armature"] == {"cases_lacking": 41, "named_falsely": 1}


def test_gear_ripple_candidate_explains_a_torque_periodic_in_the_angle(two_link):
    """A ripple 0.8 sin(2 q2) N·m left by the library: the gear-ripple candidate, fitted on the fit
    logs' residual, removes most of the check log's; on a plain noise residual it removes nothing."""
    from safesysid.systems.diagnosis.candidates import candidate_gain
    from safesysid.systems.diagnosis.problem import design_residual

    def gain(ripple):
        logs = _logs(two_link, 6, {}, noise=0.05)
        for log in logs:
            log.tau[:, 1] += ripple * np.sin(2 * log.q[:, 1])
        d = dg.diagnose(two_link, logs[:2], logs[2:], effects=("torque_offset",))
        fit = [(f, design_residual(f, d.combined_params)) for f in d.fit_designs]
        return candidate_gain(fit, list(zip(d.check_designs, d.check_residual_after)), "gear_ripple")

    g = gain(0.8)
    assert g["rms_after_per_joint"][1] < 0.3 * g["rms_before_per_joint"][1]
    g0 = gain(0.0)
    assert g0["rms_after"] > 0.95 * g0["rms_before"]


def test_hard_self_check_cli_writes_each_case_as_it_finishes(tmp_path):
    import json

    from safesysid.cli import main

    out = tmp_path / "hard"
    assert main(["diagnose", "--self-check", "--hard", "--cases", "1", "--seed", "3", "--out", str(out)]) == 0
    res = json.loads((out / "self_check.json").read_text())
    assert res["hard"] and res["cases"][0]["injected"] == [] and res["cases"][0]["named"] == []
    assert res["summary"]["targets"]["hard_cases_with_false_effect<=0.01"]
    assert len((out / "cases.jsonl").read_text().splitlines()) == 1
    assert "false naming: 0.0% of 1 null" in (out / "confusion.md").read_text()
