"""The diagnosis self-check's hard mode, read back: false naming (null and non-null cases, per
library effect, with a 95 % Clopper-Pearson interval), ambiguity reports, and the statistical
intervals' coverage: as recorded (with intervals.CALIBRATION as committed when the run was
made), and with per-effect factors chosen on the even cases and scored on the odd ones.

    safesysid diagnose --self-check --hard --cases 200 --seed 301 --workers 2 --out DIR
    python experiments/hard_self_check.py DIR/cases.jsonl   (also reads a partial run)
    python experiments/hard_self_check.py DIR/cases.jsonl --calibration CAL/cases.jsonl
        factors chosen on every case of another run (CAL) and the even cases of DIR, coverage on
        DIR's odd cases; the factors printed are what intervals.CALIBRATION holds
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from safesysid.systems.diagnosis.truth_scores import calibrated_coverage, coverage_table, spurious_table
from scipy.stats import beta


def read_cases(path: str | Path) -> list[dict]:
    p = Path(path)
    if p.suffix == ".jsonl":
        return [json.loads(line) for line in p.read_text().splitlines() if line.strip()]
    return json.loads(p.read_text())["cases"]


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact binomial confidence interval of a rate k / n."""
    a = (1 - level) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def _false_naming(cases):
    sp = spurious_table(cases)
    k = sum(bool(c["false"]) for c in cases)
    lo, hi = clopper_pearson(k, len(cases))
    print(
        f"{sp['cases']} hard cases: spurious effect in {100 * sp['null_with_false_effect']:.1f} % of "
        f"{sp['null_cases']} null and {100 * sp['non_null_with_false_effect']:.1f} % of {sp['non_null_cases']} "
        f"non-null cases ({k} cases, {100 * sp['all_with_false_effect']:.1f} % of all, 95 % CI "
        f"{100 * lo:.1f}-{100 * hi:.1f} %); reported ambiguous: {sp['cases_reported_ambiguous']}"
    )
    u = sp["false_not_flagged"]
    print(
        f"false and not flagged (no ambiguity report offering the injected set): {u} cases "
        f"({100 * u / len(cases):.1f} %, 95 % CI {100 * clopper_pearson(u, len(cases))[0]:.1f}-"
        f"{100 * clopper_pearson(u, len(cases))[1]:.1f} %)"
    )
    _exact_naming(cases)
    missed = sum(len(c["missed"]) for c in cases)
    print(f"injected effects missed: {missed} of {sum(len(c['injected']) for c in cases)}")
    for c in cases:
        if c["false"]:
            print(f"  case {c['case']}: injected {', '.join(c['injected']) or 'none'} -> named {', '.join(c['named'])}")
    print("| effect | cases lacking it | named there |\n|---|---|---|")
    for e, row in sp["per_effect"].items():
        print(f"| {e} | {row['cases_lacking']} | {row['named_falsely']} |")


def _exact_naming(cases):
    """Cases named exactly (the injected set, nothing else), in all cases and in those not reported
    ambiguous, beside what naming the best set whole would give (named + unresolved: the rule
    before the contested effects were left unnamed; cases run before it record no `unresolved`)."""
    exact = lambda c, named: set(named) == set(c["injected"])  # noqa: E731
    whole = [c["named"] + c.get("unresolved", []) for c in cases]
    clear = [k for k, c in enumerate(cases) if not c.get("ambiguous")]
    n_exact = sum(exact(c, c["named"]) for c in cases)
    n_whole = sum(exact(c, w) for c, w in zip(cases, whole))
    false_whole = sum(bool(set(w) - set(c["injected"])) for c, w in zip(cases, whole))
    n_clear = sum(exact(cases[k], cases[k]["named"]) for k in clear)
    print(
        f"named exactly: {n_exact} of {len(cases)} cases ({100 * n_exact / len(cases):.1f} %), "
        f"{n_clear} of {len(clear)} not reported ambiguous ({100 * n_clear / max(len(clear), 1):.1f} %); "
        f"with unresolved effects: {sum(bool(c.get('unresolved')) for c in cases)} cases; naming the best set "
        f"whole instead: exactly {n_whole} ({100 * n_whole / len(cases):.1f} %), a false effect in {false_whole}"
    )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    cases = read_cases(argv[0])
    calibration = read_cases(argv[argv.index("--calibration") + 1]) if "--calibration" in argv else []
    _false_naming(cases)
    rec = coverage_table(cases)
    rate = rec["rate"]
    print(
        f"90 % intervals as recorded: {rec['covered']} of {rec['values']} values in {rec['cases']} cases, "
        f"coverage {'-' if rate is None else f'{100 * rate:.1f} %'}"
    )
    print("| effect | values | coverage as recorded |\n|---|---|---|")
    for e, row in rec["per_effect"].items():
        print(f"| {e} | {row['values']} | {100 * row['rate']:.0f} % |")
    cov = calibrated_coverage(cases, calibration_cases=calibration)
    rate = cov["held_out_rate"]
    where = "the even cases" + (f" and {len(calibration)} cases of the calibration run" if calibration else "")
    print(
        f"90 % intervals widened per effect as chosen on {where} ({cov['validation_values']} values), on "
        f"held-out (odd) cases: {cov['held_out_values']} values in {cov['held_out_cases']} cases, coverage "
        f"{'-' if rate is None else f'{100 * rate:.1f} %'}"
    )
    print("| effect | factor | held-out values | coverage |\n|---|---|---|---|")
    for e, f in cov["factors"].items():
        row = cov["held_out_per_effect"].get(e, {"values": 0, "rate": float("nan")})
        print(f"| {e} | {f:.2f} | {row['values']} | {100 * row['rate']:.0f} % |")
    print("CALIBRATION = " + json.dumps({e: round(f, 2) for e, f in cov["factors"].items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
