"""The paper's identification results from a compare of ours and random: Table IV (cond(Y) per
dumbbell, median and spread over trials, beside the paper's numbers), the per-parameter interval
width ratios ours/random over paired runs (same dumbbell and trial, so the same seed), and Fig. 5
per dumbbell (the ten intervals of each method against the truth and the prior).

Written by `safesysid compare ... --methods ours,random` as table_iv.md / .csv / .json and
fig5_<dumbbell>.png."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
from safesysid.report import plot_intervals_side_by_side
from safesysid.systems.model.inertial import NAMES

# The paper's Table IV: 2-norm cond(Y) over the 7.5 s identification phase (one run per dumbbell).
PAPER_COND_Y = {
    "4lb": (274.030, 479.573),
    "5lb": (282.840, 418.078),
    "6lb": (250.704, 373.448),
    "7lb": (258.517, 312.352),
    "8lb": (233.539, 413.381),
}
METHODS = ("ours", "random")


def _width(summary: dict) -> np.ndarray:
    return np.asarray(summary["estimate"]["upper"]) - np.asarray(summary["estimate"]["lower"])


def paired_runs(done: list[dict], dumbbell: str | None = None) -> list[tuple[dict, dict]]:
    """(ours, random) summaries of the same dumbbell and trial (the same seed), sorted."""
    by_key = {(s["method"], s["dumbbell"], int(s["trial"])): s for s in done}
    keys = sorted({(d, k) for m, d, k in by_key if m == "ours" and (dumbbell is None or d == dumbbell)})
    return [(by_key["ours", d, k], by_key["random", d, k]) for d, k in keys if ("random", d, k) in by_key]


def width_ratio_summary(ours: np.ndarray, rand: np.ndarray) -> dict:
    """Per parameter over paired widths (one row per pair): median width ours/random, the fraction
    of pairs where ours is strictly narrower, and how many parameters' median ratio is below 1."""
    if len(ours) == 0:
        return {"pairs": 0, "median": [], "won": [], "parameters_below_1": 0}
    ratios = np.asarray(ours) / np.asarray(rand)
    median = np.median(ratios, 0)
    return {
        "pairs": len(ratios),
        "median": median.tolist(),
        "won": np.mean(ratios < 1, 0).tolist(),
        "parameters_below_1": int(np.sum(median < 1)),
    }


def width_ratios(pairs: list[tuple[dict, dict]]) -> dict:
    """width_ratio_summary of the published intervals of (ours, random) summaries."""
    return width_ratio_summary([_width(o) for o, _ in pairs], [_width(r) for _, r in pairs])


def _spread(values: list[float]) -> dict:
    if not values:
        return {"median": None, "min": None, "max": None, "values": []}
    return {"median": float(np.median(values)), "min": min(values), "max": max(values), "values": values}


def table_iv(done: list[dict], dumbbells: list[str]) -> dict:
    """table_iv.json: per dumbbell cond(Y) of each method over its trials, the pairs where ours'
    is lower, the paper's values; per-parameter width ratios per dumbbell and over all pairs."""
    rows = {}
    for d in dumbbells:
        pairs = paired_runs(done, d)
        rows[d] = {
            **{
                m: _spread([float(s["cond_Y"]) for s in done if s["method"] == m and s["dumbbell"] == d])
                for m in METHODS
            },
            "ours_lower": sum(ours["cond_Y"] < rand["cond_Y"] for ours, rand in pairs),
            "pairs": len(pairs),
            "paper": dict(zip(METHODS, PAPER_COND_Y[d])) if d in PAPER_COND_Y else None,
            "width_ratio": width_ratios(pairs),
        }
    everything = paired_runs([s for s in done if s["dumbbell"] in dumbbells])
    return {"parameters": list(NAMES), "dumbbells": rows, "width_ratio": width_ratios(everything)}


def _cond_text(entry: dict) -> str:
    if entry["median"] is None:
        return "-"
    return f"{entry['median']:.0f} [{entry['min']:.0f}-{entry['max']:.0f}]"


def _ratio_lines(doc: dict) -> list[str]:
    r = doc["width_ratio"]
    if not r["pairs"]:
        return []
    return [
        "",
        f"Interval width ours / random per parameter over {r['pairs']} paired runs (published intervals; "
        f"median below 1 on {r['parameters_below_1']}/10):",
        "",
        "| | " + " | ".join(NAMES) + " |",
        "|" + "---|" * (len(NAMES) + 1),
        "| median ratio | " + " | ".join(f"{x:.3f}" for x in r["median"]) + " |",
        "| pairs won | " + " | ".join(f"{x:.2f}" for x in r["won"]) + " |",
    ]


def write_table_iv(out: Path, scenario_name: str, doc: dict) -> None:
    """table_iv.md / .csv / .json in the paper's layout: a row per dumbbell, cond(Y) ours | random
    (median [min-max] over trials), pairs where ours is lower, the paper's two values."""
    head = ["dumbbell", "ours cond(Y)", "random cond(Y)", "ours lower", "paper ours", "paper random"]
    rows = []
    for d, row in doc["dumbbells"].items():
        paper = row["paper"] or {}
        rows.append(
            [d, _cond_text(row["ours"]), _cond_text(row["random"]), f"{row['ours_lower']}/{row['pairs']}"]
            + [f"{paper[m]:.1f}" if m in paper else "-" for m in METHODS]
        )
    lines = [
        f"# {scenario_name}: Table IV, cond(Y) over the identification phase (median [min-max] over trials)",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
        *("| " + " | ".join(r) + " |" for r in rows),
        *_ratio_lines(doc),
    ]
    (out / "table_iv.md").write_text("\n".join(lines) + "\n")
    with (out / "table_iv.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(head)
        writer.writerows(rows)
    (out / "table_iv.json").write_text(json.dumps({"scenario": scenario_name, **doc}, indent=2))


def write_identification_results(
    out: Path, scenario_name: str, done: list[dict], *, dumbbells: list[str], prior: tuple
) -> list[Path]:
    """Table IV and one Fig. 5 per dumbbell (its first trial with both methods) when the compare
    ran ours and random; nothing otherwise. Returns the paths written."""
    done = [s for s in done if s["method"] in METHODS]
    if not paired_runs(done):
        return []
    write_table_iv(out, scenario_name, table_iv(done, dumbbells))
    written = [out / f"table_iv.{ext}" for ext in ("md", "csv", "json")]
    for d in dumbbells:
        pairs = paired_runs(done, d)
        if pairs:
            ours = pairs[0][0]
            estimates = {
                m: [s["estimate"][k] for k in ("nominal", "lower", "upper")] for m, s in zip(METHODS, pairs[0])
            }
            title = f"{scenario_name}, {d}, trial {ours['trial']}: intervals after identification (Fig. 5)"
            path = out / f"fig5_{d}.png"
            written.append(
                plot_intervals_side_by_side(path, estimates, ours["payload_true"]["theta"], title=title, prior=prior)
            )
    return written
