"""Plots and tables of a closed-loop run (matplotlib, Agg backend)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from safesysid.systems.model.inertial import NAMES, UNITS  # noqa: E402
from safesysid.viz import PHASE_COLOURS  # noqa: E402


def save_figure(fig: plt.Figure, path: str | Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_tracking(
    path: str | Path, t: np.ndarray, error: np.ndarray, *, bound: np.ndarray, torque_ratio: np.ndarray
) -> Path:
    """Per-joint |e_i| / bound_i (1 = the certified ultimate bound), and max |u|/limit."""
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    ax1.plot(t, np.abs(error) / np.asarray(bound), lw=0.8, label=[f"joint {k + 1}" for k in range(error.shape[1])])
    ax1.axhline(1.0, color="k", ls="--", label="ultimate bound")
    ax1.set_ylabel("|q_d - q| / bound")
    ax1.legend(loc="upper right", fontsize=7, ncol=4)
    ax2.plot(t, torque_ratio, lw=0.8)
    ax2.axhline(1.0, color="k", ls="--")
    ax2.set_ylabel("max |u| / limit")
    ax2.set_xlabel("t [s]")
    return save_figure(fig, path)


CLEARANCE_TITLE = "least distance between the links' own shapes (+ payload) and the obstacles and floor"


def plot_clearance(
    path: str | Path, t: np.ndarray, clearance: np.ndarray, *, phases: Sequence[tuple[str, float, float]] = ()
) -> Path:
    """The referee's clearance (Drake signed distance on the link shapes), the phases shaded."""
    fig, ax = plt.subplots(figsize=(8, 3.2))
    shade_phases(ax, list(phases))
    ax.plot(t, clearance, label="clearance")
    ax.axhline(0.0, color="r", ls="--", label="contact")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("signed distance [m]")
    ax.set_title(CLEARANCE_TITLE, fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    return save_figure(fig, path)


def plot_intervals(
    path: str | Path,
    nominal: np.ndarray,
    lower: np.ndarray,
    *,
    upper: np.ndarray,
    truth: np.ndarray | None = None,
    title: str = "",
    prior: tuple | None = None,
) -> Path:
    """The 10 end-effector intervals with nominal (and truth), like the paper's Fig. 5; the prior
    (lower, upper) as a grey band, so a parameter the data did not narrow shows as such."""
    return plot_intervals_side_by_side(path, {"estimate": (nominal, lower, upper)}, truth, title=title, prior=prior)


def plot_intervals_side_by_side(
    path: str | Path,
    estimates: dict[str, tuple],
    truth: np.ndarray | None = None,
    *,
    title: str = "",
    prior: tuple | None = None,
) -> Path:
    """Fig. 5: per parameter, each estimate's interval and nominal side by side (estimates:
    {label: (nominal, lower, upper)}), the truth when known and the prior's (lower, upper) as a band."""
    fig, axes = plt.subplots(2, 5, figsize=(13 + len(estimates), 5.5))
    labels = list(estimates)
    for k, ax in enumerate(axes.ravel()):
        if prior is not None:
            ax.axhspan(prior[0][k], prior[1][k], color="0.9", label="prior")
        for i, label in enumerate(labels):
            nominal, lo, hi = (np.asarray(x, float) for x in estimates[label])
            mid, half = 0.5 * (lo[k] + hi[k]), 0.5 * (hi[k] - lo[k])
            ax.errorbar([i], [mid], yerr=[[half]], fmt="none", capsize=8, color=f"C{i}")
            ax.plot([i], [nominal[k]], "o", color=f"C{i}", ms=5)
        if truth is not None:
            ax.plot(range(len(labels)), [truth[k]] * len(labels), "r*", ms=11, label="truth")
        ax.set_title(f"{NAMES[k]} [{UNITS[k]}]", fontsize=9)
        ax.set_xticks(range(len(labels)), labels, fontsize=8)  # the method stays named when it is alone
        ax.set_xlim(-0.6, len(labels) - 0.4)
    if truth is not None or prior is not None:
        axes[0, 0].legend(fontsize=8)
    fig.suptitle(title)
    return save_figure(fig, path)


def plot_estimate_history(
    path: str | Path,
    times: np.ndarray,
    nominal: np.ndarray,
    *,
    lower: np.ndarray,
    upper: np.ndarray,
    truth: np.ndarray | None = None,
    index: int = 0,
    prior: tuple | None = None,
    title: str = "",
) -> Path:
    """Evolution of one parameter's estimate and interval over the updates (default: mass), the
    prior (lower, upper) as a band behind it."""
    fig, ax = plt.subplots(figsize=(8, 3.4))
    if prior is not None:
        ax.axhspan(prior[0][index], prior[1][index], color="0.9", label="prior")
    ax.fill_between(
        times, np.asarray(lower)[:, index], np.asarray(upper)[:, index], step="post", alpha=0.3, label="interval"
    )
    ax.step(times, np.asarray(nominal)[:, index], where="post", label="estimate")
    if truth is not None:
        ax.axhline(truth[index], color="r", ls="--", label="truth")
    ax.set_xlabel("t [s]")
    ax.set_ylabel(f"{NAMES[index]} [{UNITS[index]}]")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def identified_body_text(truth_mass_kg: float, dumbbell: str | None, dumbbell_kg: float | None) -> str:
    """What the identified mass is: the end-effector body is the last link + gripper + payload."""
    if not dumbbell or dumbbell_kg is None:
        return f"identified body: last link + gripper ({truth_mass_kg:.3f} kg, no payload)"
    return (
        f"identified body: last link + gripper {truth_mass_kg - dumbbell_kg:.3f} kg "
        f"+ {dumbbell} dumbbell {dumbbell_kg:.3f} kg = {truth_mass_kg:.3f} kg"
    )


def markdown_table(rows: Sequence[dict], columns: Sequence[str]) -> str:
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    fmt = lambda x: f"{x:.4g}" if isinstance(x, float) else str(x)  # noqa: E731
    return head + "".join("| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |\n" for r in rows)


def shade_phases(ax: plt.Axes, phases: list[tuple[str, float, float]], label: bool = True) -> None:
    for name, t0, t1 in phases:
        ax.axvspan(t0, t1, color=PHASE_COLOURS.get(name, "#999"), alpha=0.08, lw=0)
        if label:
            ax.text(
                0.5 * (t0 + t1), 1.0, name, transform=ax.get_xaxis_transform(), ha="center", va="bottom", fontsize=7
            )
