"""`safesysid bench` hook of benchmarks/interval_budget.py (the quick case: one run, ~10 s)."""

from __future__ import annotations

from safesysid.benchmarks import interval_budget


def run(quick: bool = False) -> dict:
    return interval_budget.run(quick=True)
