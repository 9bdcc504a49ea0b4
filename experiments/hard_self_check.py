"""The diagnosis self-check's hard mode, read back: false naming (null and non-null cases, per
library effect), ambiguity reports, and the statistical intervals' coverage with the per-effect
factors chosen on the even cases and scored on the odd ones.

    safesysid diagnose --self-check --hard --cases 200 --seed 301 --workers 2 --out DIR
    python experiments/hard_self_check.py DIR/cases.jsonl   (also reads a partial run)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from safesysid.systems.diagnosis.truth_scores import calibrated_coverage, spurious_table


def read_cases(path: str | Path) -> list[dict]:
    p = Path(path)
    if p.suffix == ".jsonl":
        return [json.loads(line) for line in p.read_text().splitlines() if line.strip()]
    return json.loads(p.read_text())["cases"]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    cases = read_cases(argv[0])
    sp = spurious_table(cases)
    print(
        f"{sp['cases']} hard cases: spurious effect in {100 * sp['null_with_false_effect']:.1f} % of "
        f"{sp['null_cases']} null and {100 * sp['non_null_with_false_effect']:.1f} % of {sp['non_null_cases']} "
        f"non-null cases ({100 * sp['all_with_false_effect']:.1f} % of all); reported ambiguous: "
        f"{sp['cases_reported_ambiguous']}"
    )
    print("| effect | cases lacking it | named there |\n|---|---|---|")
    for e, row in sp["per_effect"].items():
        print(f"| {e} | {row['cases_lacking']} | {row['named_falsely']} |")
    cov = calibrated_coverage(cases)
    rate = cov["held_out_rate"]
    print(
        f"90 % intervals on held-out (odd) cases: {cov['held_out_values']} values in {cov['held_out_cases']} "
        f"cases, coverage {'-' if rate is None else f'{100 * rate:.1f} %'}"
    )
    print("| effect | factor (even cases) | held-out values | coverage |\n|---|---|---|---|")
    for e, f in cov["factors"].items():
        row = cov["held_out_per_effect"].get(e, {"values": 0, "rate": float("nan")})
        print(f"| {e} | {f:.2f} | {row['values']} | {100 * row['rate']:.0f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
