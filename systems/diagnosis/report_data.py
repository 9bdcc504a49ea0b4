"""Where the gap lies, for diagnosis.json: motion regimes, worst time windows, speed-saturated
spans, and the contract fields on scored logs; the report's sentence on effects left unnamed.
"""

from __future__ import annotations

import numpy as np

from .design import Design
from .selection import Z_NAME, contested

REGIME_QUANTILE = 0.75
POSE_BINS = 4


def regimes(
    designs: list[Design], residuals: list[np.ndarray]
) -> tuple[dict[str, float], dict[str, float], list[dict]]:
    """Share of the squared residual per motion regime (per joint element) and per time window."""
    r2 = np.concatenate(residuals) ** 2
    total = r2.sum() or 1.0
    masks = regime_masks(designs)
    share = {k: float(r2[m].sum() / total) for k, m in masks.items()}
    samples = {k: float(m.mean()) for k, m in masks.items()}
    windows = []
    for d, r in zip(designs, residuals):
        tt = d.row_time
        edges = np.arange(tt[0], tt[-1] + 1.0, 1.0)
        idx = np.digitize(tt, edges) - 1
        for w in np.unique(idx):
            sel = idx == w
            windows.append(
                {
                    "log": d.source,
                    "t_start": float(edges[w]),
                    "t_end": float(edges[w] + 1.0),
                    "share": float((r[sel] ** 2).sum() / total),
                }
            )
    windows.sort(key=lambda x: -x["share"])
    return share, samples, windows[:5]


def regime_masks(designs: list[Design]) -> dict[str, np.ndarray]:
    """(rows, n) masks of the motion regimes: near-zero velocity, within 0.1 s of a velocity
    reversal, the top quarter of |a|, |v| and |gravity torque| per joint, speed-saturated."""
    v = np.concatenate([d.features["v"] for d in designs])
    a = np.concatenate([d.features["a"] for d in designs])
    g = np.concatenate([d.features["g"] for d in designs])
    vmax = np.abs(v).max(0)
    near_zero = np.abs(v) < np.maximum(0.02, 0.05 * vmax)
    rev = np.zeros_like(near_zero)
    base = 0
    for d in designs:
        vv = d.features["v"]
        tt = d.row_time
        sign_change = np.zeros(vv.shape, bool)
        sign_change[1:] = np.sign(vv[1:]) * np.sign(vv[:-1]) < 0
        for j in range(vv.shape[1]):
            ts = tt[sign_change[:, j]]
            if len(ts):
                dist = np.min(np.abs(tt[:, None] - ts[None, :]), axis=1)
                rev[base : base + len(tt), j] = dist <= 0.1
        base += len(tt)
    return {
        "near_zero_velocity": near_zero,
        "reversal": rev,
        "high_acceleration": np.abs(a) >= np.quantile(np.abs(a), REGIME_QUANTILE, axis=0),
        "high_speed": np.abs(v) >= np.quantile(np.abs(v), REGIME_QUANTILE, axis=0),
        "high_gravity_load": np.abs(g) >= np.quantile(np.abs(g), REGIME_QUANTILE, axis=0),
        # Joint at its speed limit (velocity_saturation): the logged torque is not delivered.
        "velocity_saturation": np.concatenate([d.row_saturated for d in designs]),
    }


def residual_map(designs: list[Design], residuals: list[np.ndarray], pose_bins: int = POSE_BINS) -> dict:
    """Where a residual lies, per joint: its RMS and share of the total squared residual, and per
    regime (regime_masks) and per joint-angle bin (equal-count bins of that joint's angle) the
    share of that joint's squared residual beside the share of its samples (a ratio above 1:
    the residual concentrates there)."""
    r2 = np.concatenate(residuals) ** 2
    q = np.concatenate([d.features["q"] for d in designs])
    masks = regime_masks(designs)
    total = r2.sum() or 1.0
    joints = []
    for j in range(r2.shape[1]):
        rj = r2[:, j]
        tj = rj.sum() or 1.0
        edges = np.quantile(q[:, j], np.linspace(0, 1, pose_bins + 1))
        idx = np.clip(np.searchsorted(edges, q[:, j], side="right") - 1, 0, pose_bins - 1)
        joints.append(
            {
                "joint": j + 1,
                "rms": float(np.sqrt(rj.mean())),
                "share": float(rj.sum() / total),
                "regimes": {
                    k: {"share": float(rj[m[:, j]].sum() / tj), "samples": float(m[:, j].mean())}
                    for k, m in masks.items()
                },
                "pose_bins": [
                    {
                        "q_from_rad": float(edges[b]),
                        "q_to_rad": float(edges[b + 1]),
                        "share": float(rj[idx == b].sum() / tj),
                        "samples": float(np.mean(idx == b)),
                    }
                    for b in range(pose_bins)
                ],
            }
        )
    return {"joints": joints, "pose_bins": pose_bins}


def held_out_result(
    designs: list[Design],
    before: list[np.ndarray],
    after: list[np.ndarray],
    *,
    test: dict,
    entries: list[dict],
    form: str,
) -> dict:
    """The contract fields of diagnosis.json (gap, effects, cause, combined) on scored logs."""
    named = [e["name"] for e in entries if e["significant"]]
    share, samples, windows = regimes(designs, before)
    return {
        "gap": {
            "rms_check": test["rms_before"],
            "rms_check_per_joint": test["rms_before_per_joint"],
            "where": {
                "joints": [int(j) + 1 for j in np.argsort(-np.array(test["rms_before_per_joint"]))],
                "regimes": share,
                "regime_sample_share": samples,
                "time_windows": windows,
            },
            "residual_form": form,
            "rms_check_per_log": test["rms_before_per_log"],
            "velocity_saturation": _saturation_summary(designs, before),
        },
        "effects": entries,
        "cause": named,
        "combined": {
            "effects": named,
            "rms_check_after": test["rms_after"],
            "reduction": test["reduction"],
            "rms_check_per_joint_after": test["rms_after_per_joint"],
            "rms_check_per_log_after": test["rms_after_per_log"],
            "regimes_after": regimes(designs, after)[0],
            "residual_map_after": residual_map(designs, after),
            "without_saturated": {
                "rms_check": test["without_saturated"]["rms_before"],
                "rms_check_after": test["without_saturated"]["rms_after"],
                "reduction": test["without_saturated"]["reduction"],
            },
        },
    }


def _saturation_summary(designs, residuals):
    """Where joints ran at their speed limit in the check logs and the residual share there."""
    sat = np.concatenate([d.row_saturated for d in designs])
    r2 = np.concatenate(residuals) ** 2
    spans = []
    for d in designs:
        for j in range(sat.shape[1]):
            m = np.concatenate([[False], d.row_saturated[:, j], [False]]).astype(int)
            for i0, i1 in zip(np.flatnonzero(np.diff(m) == 1), np.flatnonzero(np.diff(m) == -1) - 1):
                spans.append(
                    {
                        "log": d.source,
                        "joint": j + 1,
                        "t_start": float(d.row_time[i0]),
                        "t_end": float(d.row_time[i1]),
                        "speed_rad_s": float(np.abs(d.features["v"][i0 : i1 + 1, j]).mean()),
                    }
                )
    return {
        "element_share": float(sat.mean()),
        "per_joint_share": [float(x) for x in sat.mean(0)],
        "residual_share": float(r2[sat].sum() / (r2.sum() or 1.0)),
        "spans": spans,
    }


def unresolved_text(result: dict) -> str:
    """The best set's effects left unnamed (diagnosis.json `unresolved`), the rival sets that
    explain the fit logs as well and the data that would separate them; empty when none."""
    unresolved = result.get("unresolved") or []
    if not unresolved:
        return ""
    selected = result["cause"] + unresolved
    rivals = [
        a
        for a in result["ambiguous"]
        if contested(
            a["sets"][0]["effects"], [{"effects": a["sets"][1]["effects"], "difference_z": a["difference_z"]}], selected
        )
    ]
    sets = " or ".join(" + ".join(a["sets"][1]["effects"]) for a in rivals)
    verb = "explains" if len(rivals) == 1 else "explain"
    separate = "; ".join(dict.fromkeys(a["separating_data"] for a in rivals))
    return (
        f" **Not named:** {', '.join(unresolved)}: {sets} {verb} the fit logs as well (within {Z_NAME:g} "
        f"standard error), so the logs cannot tell which acts; data that would separate them: {separate}."
    )
