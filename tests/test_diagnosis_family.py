"""A growing effect library must not buy false positives: a greedy addition is the best of the
K candidates left, so its significance is judged at the family-wise level
(selection.family_levels), not as if it were the only test."""

import numpy as np
import pytest
from safesysid.systems.diagnosis import selection as S
from safesysid.systems.diagnosis.effects import EFFECTS
from scipy.stats import norm


class _Evaluator:
    """A linear stand-in for CrossValidated on one joint: each effect one column, fitted on the
    first half of the rows and validated on the second."""

    def __init__(self, X: dict[str, np.ndarray], y: np.ndarray, blocks: int = 24):
        half = len(y) // 2
        self.X, self.y, self.half = X, y, half
        self.n, self.n_fit_rows, self.min_delay = 1, half, 0.0
        self.check_block = np.arange(len(y) - half) * blocks // (len(y) - half)
        self.check_joint = np.zeros(len(y) - half, int)
        self.tau_rms_check = np.array([10.0])
        self.y_check, self.yy, self.empty = y[half:], float(y[:half] @ y[:half]), {}

    def fit_effects(self, effects):
        if not effects:
            return {}, self.yy
        A = np.stack([self.X[e][: self.half] for e in effects], 1)
        p, *_ = np.linalg.lstsq(A, self.y[: self.half], rcond=None)
        r = self.y[: self.half] - A @ p
        return {e: p[k : k + 1] for k, e in enumerate(effects)}, float(r @ r)

    def check_residual(self, params):
        r = self.y_check.copy()
        for e, p in params.items():
            r -= self.X[e][self.half :] * p[0]
        return r


def test_family_levels_hold_the_chance_of_any_false_pass():
    """With k candidates, the chance that the best of k null z-scores passes stays near the
    single-test level, while the single-test threshold lets it grow about k-fold."""
    for k in (1, 5, 10):
        z, p = S.family_levels(k)
        assert 1 - (1 - norm.sf(z)) ** k <= S.P_BLOCKS / S.FAMILY_TESTS * 1.0001
        assert p == S.P_BLOCKS / (S.FAMILY_TESTS * k)
    assert 1 - (1 - norm.sf(S.Z_BLOCK)) ** 10 > 9 * S.P_BLOCKS
    assert S.family_levels(0) == (S.Z_BLOCK, S.P_BLOCKS)


def test_a_modest_gain_passes_alone_but_not_as_the_best_of_nine():
    """A candidate whose held-out gain is 3.5 standard errors: significant as a single test (the
    old rule for every greedy step), not as the best of nine (family-wise)."""
    rows = 600
    rng = np.random.default_rng(0)
    ev = _Evaluator({}, np.zeros(2 * rows))
    r1 = rng.normal(size=rows)
    r0 = r1 + 0.45 * np.sin(np.arange(rows) / 7.0)
    single = S.significance(ev, r0, r1, 100.0, 90.0, 1)
    assert 3.0 < single["z"] < 3.7 and single["p_blocks"] > S.family_levels(9)[1]
    assert single["significant"]
    assert not S.significance(ev, r0, r1, 100.0, 90.0, 1, family=9)["significant"]


def test_greedy_additions_are_judged_as_the_best_of_the_candidates_left(monkeypatch):
    """Two strong effects make the best pair; each greedy step past it tests every library
    effect left and must say so (family = their number)."""
    rng = np.random.default_rng(1)
    m = 2400
    X = {e: rng.normal(size=m) for e in EFFECTS}
    y = 3 * X["viscous_friction"] + 2 * X["armature"] + rng.normal(size=m)
    calls = []
    real = S.significance

    def spy(*args, family=0, **kwargs):
        calls.append(family)
        return real(*args, family=family, **kwargs)

    monkeypatch.setattr(S, "significance", spy)
    sel = S.select_effects(_Evaluator(X, y), list(EFFECTS), max_effects=6)
    assert set(sel.effects) == {"viscous_friction", "armature"}
    assert calls.count(len(EFFECTS) - 2) == len(EFFECTS) - 2  # one greedy step, every candidate left


def _case(k, *, fitted=0.9, ran_with=None, false=(), ambiguous=()):
    """A coverage record: truth 1.0, interval fitted +- 0.05 (0.9 needs 2x widening)."""
    rec = {"effect": "time_delay", "key": "delay_s", "index": None, "truth": 1.0}
    c = {
        "case": k,
        "injected": ["time_delay", "armature"],
        "false": list(false),
        "ambiguous": [list(a) for a in ambiguous],
        "fitted": {"time_delay": {"delay_s": fitted}},
        "coverage": [{**rec, "lo": fitted - 0.05, "hi": fitted + 0.05}],
    }
    if ran_with is not None:
        c["interval_calibration"] = {"time_delay": ran_with}
    return c


def test_factors_are_relative_to_the_raw_interval_and_may_come_from_another_run():
    """A run made with a calibration factor records intervals already widened by it: the factor
    chosen again is relative to the raw sandwich (not compounded), and a calibration run's cases
    choose factors alongside the even cases without being scored."""
    from safesysid.systems.diagnosis.truth_scores import calibrated_coverage

    raw = [_case(k) for k in range(20)]  # each value needs 2x
    widened = [_case(k, fitted=0.9, ran_with=2.0) for k in range(20)]  # recorded +- 0.05 after 2x: needs 4x raw
    assert calibrated_coverage(raw)["factors"]["time_delay"] == pytest.approx(2.0)
    assert calibrated_coverage(widened)["factors"]["time_delay"] == pytest.approx(4.0)
    cov = calibrated_coverage([_case(k, fitted=0.98) for k in range(20)], calibration_cases=raw)
    assert (
        cov["factors"]["time_delay"] == pytest.approx(2.0)
        and cov["held_out_values"] == 10
        and cov["validation_values"] == 30
    )


def test_a_false_name_is_flagged_only_when_the_ambiguity_report_offers_the_truth():
    from safesysid.systems.diagnosis.truth_scores import spurious_table

    cases = [
        _case(0, false=["torque_scale"], ambiguous=[["armature", "time_delay"]]),  # truth offered
        _case(1, false=["torque_scale"], ambiguous=[["armature", "payload"]]),  # another set
        _case(2, false=["torque_scale"]),
        _case(3),
    ]
    sp = spurious_table(cases)
    assert sp["cases_reported_ambiguous"] == 2 and sp["false_not_flagged"] == 2
