"""Plots (matplotlib, Agg) of a gap diagnosis: residual against motion quantities per joint,
before/after time series, per-joint bars."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from safesysid.systems.diagnosis import Diagnosis


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _grid(n):
    cols = min(4, n)
    return (n + cols - 1) // cols, cols


def write_plots(out: str | Path, diagnosis: Diagnosis) -> dict[str, str]:
    """Residual vs velocity / acceleration / gravity torque per joint, before/after time series,
    per-joint bars. Returns {name: filename}."""
    plt = _plt()
    out = Path(out)
    d = diagnosis
    check = d.check_designs
    n = check[0].y.shape[1]
    before = np.concatenate(d.check_residual_before)
    after = np.concatenate(d.check_residual_after)
    files = {}
    feats = {
        "velocity": ("v", "velocity [rad/s]"),
        "acceleration": ("a", "acceleration [rad/s²]"),
        "gravity": ("g", "gravity torque [N·m]"),
    }
    for key, (f, label) in feats.items():
        x = np.concatenate([c.features[f] for c in check])
        rows, cols = _grid(n)
        fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
        for j in range(rows * cols):
            ax = axes.flat[j]
            if j >= n:
                ax.axis("off")
                continue
            ax.scatter(x[:, j], before[:, j], s=2, c="0.6", label="nominal")
            ax.scatter(x[:, j], after[:, j], s=2, c="tab:blue", label="corrected")
            ax.set_title(f"joint {j + 1}", fontsize=9)
            ax.set_xlabel(label, fontsize=8)
            ax.tick_params(labelsize=7)
            if j % cols == 0:
                ax.set_ylabel("residual [N·m]", fontsize=8)
        axes.flat[0].legend(fontsize=7, markerscale=4)
        fig.suptitle(f"Held-out residual vs {key}", fontsize=10)
        fig.tight_layout()
        name = f"residual_vs_{key}.png"
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        files[key] = name
    # Time series of the first check log.
    c0 = check[0]
    fig, axes = plt.subplots(n, 1, figsize=(9, 1.4 * n + 0.6), sharex=True, squeeze=False)
    for j in range(n):
        ax = axes[j, 0]
        ax.plot(c0.row_time, d.check_residual_before[0][:, j], lw=0.6, c="0.5", label="nominal")
        ax.plot(c0.row_time, d.check_residual_after[0][:, j], lw=0.6, c="tab:blue", label="corrected")
        if c0.row_saturated[:, j].any():
            ax.fill_between(
                c0.row_time,
                0,
                1,
                where=c0.row_saturated[:, j],
                color="tab:orange",
                alpha=0.25,
                transform=ax.get_xaxis_transform(),
                label="speed-saturated",
            )
        ax.set_ylabel(f"j{j + 1} [N·m]", fontsize=8)
        ax.tick_params(labelsize=7)
    handles = {h.get_label(): h for ax in axes[:, 0] for h in ax.get_legend_handles_labels()[0]}
    axes[0, 0].legend(handles.values(), handles.keys(), fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"Residual before/after, {Path(c0.source).name or 'check log 1'}", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "residual_timeseries.png", dpi=90)
    plt.close(fig)
    files["timeseries"] = "residual_timeseries.png"
    res = d.result
    if "residual_map_after" in res["combined"]:
        files["residual_map"] = residual_map_plot(out / "residual_map.png", res["combined"]["residual_map_after"])
    # Per-joint bars.
    files["bars"] = joint_bars(
        out / "joint_rms.png",
        res["gap"]["rms_check_per_joint"],
        res["combined"]["rms_check_per_joint_after"],
        label_after="corrected",
    )
    return files


def joint_bars(path: str | Path, before: Sequence[float], after: Sequence[float], *, label_after: str) -> str:
    """Per-joint held-out RMS bars, nominal vs corrected; returns the file name."""
    plt = _plt()
    idx = np.arange(len(before))
    fig, ax = plt.subplots(figsize=(7, 3))
    ax.bar(idx - 0.2, before, 0.4, color="0.6", label="nominal")
    ax.bar(idx + 0.2, after, 0.4, color="tab:blue", label=label_after)
    ax.set_xticks(idx, [f"j{j + 1}" for j in idx])
    ax.set_ylabel("held-out RMS [N·m]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path).name


def residual_map_plot(path: str | Path, residual_map: dict) -> str:
    """Heat map of where the residual left after the correction lies: per joint (rows) and per
    regime and joint-angle bin (columns), its share of that joint's residual² over the share of
    that joint's samples (1: no concentration), the joint's share of the total on the left."""
    plt = _plt()
    joints = residual_map["joints"]
    regimes = list(joints[0]["regimes"])
    bins = len(joints[0]["pose_bins"])
    ratio = lambda c: c["share"] / c["samples"] if c["samples"] > 0 else np.nan  # noqa: E731
    grid = np.array([[ratio(j["regimes"][k]) for k in regimes] + [ratio(b) for b in j["pose_bins"]] for j in joints])
    labels = [k.replace("_", " ") for k in regimes] + [f"angle bin {b + 1}" for b in range(bins)]
    fig, ax = plt.subplots(figsize=(1.0 * len(labels) + 2, 0.45 * len(joints) + 1.6))
    im = ax.imshow(grid, cmap="magma", vmin=0, vmax=max(3.0, float(np.nanmax(grid, initial=1.0))), aspect="auto")
    for (r, c), v in np.ndenumerate(grid):
        if np.isfinite(v):
            ax.text(c, r, f"{v:.1f}", ha="center", va="center", fontsize=7, color="w" if v < 2 else "k")
    ax.set_xticks(range(len(labels)), labels, rotation=40, ha="right", fontsize=7)
    ax.set_yticks(range(len(joints)), [f"j{j['joint']} ({100 * j['share']:.0f} %)" for j in joints], fontsize=7)
    fig.colorbar(im, ax=ax, label="share of residual² / share of samples")
    ax.set_title("Residual left after the correction: where it concentrates", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path).name
