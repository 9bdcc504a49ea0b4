"""Shared pieces of the scaling benchmarks: timing statistics, wall + CPU clocks, the load
average, and one PNG per scaling (matplotlib, Agg backend)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np


def load_average() -> float | None:
    """1-minute load average (None where the OS has none): the machine is shared, so every
    timing is recorded with it."""
    try:
        return float(os.getloadavg()[0])
    except (OSError, AttributeError):
        return None


def timed(fn):
    """(result, wall_s, cpu_s) of fn(); CPU = this process's time (robust to other processes)."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t0, time.process_time() - c0


def stats(times, deadline_s: float | None = None) -> dict:
    """median, p95, max (and misses of the deadline) of a list of durations [s]."""
    t = np.asarray(times, float)
    out = {"count": int(t.size), "median_s": float(np.median(t)), "p95_s": float(np.percentile(t, 95))}
    out["max_s"] = float(t.max())
    if deadline_s is not None:
        out["deadline_s"] = float(deadline_s)
        out["missed"] = int(np.sum(t > deadline_s))
    return out


def plot(
    path: Path | None, x, series: dict, xlabel: str, ylabel: str, title: str, logx: bool = False, logy: bool = False
) -> str | None:
    """One scaling plot (each series label -> y values over x, NaN skipped); returns the path."""
    if path is None:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    for label, y in series.items():
        ax.plot(x, np.asarray(y, float), marker="o", label=label)
    ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
    if logx:
        ax.set_xscale("log")
    if logy:
        ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def png(out: Path | None, name: str) -> Path | None:
    """out/name.png, or None when the caller gave no output folder (no plot written)."""
    return None if out is None else Path(out) / f"{name}.png"
