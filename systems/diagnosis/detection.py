"""Detection limits: per effect and noise level, the smallest physical size the self-check's
blind diagnosis names in >= 90 % of cases.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from safesysid.systems.math.blas import single_threaded_blas
from safesysid.systems.model.robot_model import RobotModel

from .diagnose import diagnose
from .self_check import parallel_map
from .simulate import STRIBECK_VS, make_case, payload_theta

# Physical sizes tried per effect (time_delay once per law): the smallest found in >= 90 % of
# cases at a given noise level is the detection limit. Per-joint effects act on one random joint;
# the elasticity on one of the joints whose deflection gravity sees (ELASTIC_JOINTS): on the
# others the torque does not depend on the deflection and no size is visible.
DETECTION_LADDERS = {
    "coulomb_friction": ("ΔFc", "N·m", (0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)),
    "viscous_friction": ("ΔFv", "N·m·s/rad", (0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)),
    "stribeck_friction": ("Fs", "N·m", (0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)),
    "load_friction": ("μ", "-", (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2)),
    "armature": ("ΔIa", "kg·m²", (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)),
    "torque_offset": ("offset", "N·m", (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)),
    "torque_scale": ("scale deviation from 1", "-", (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1)),
    "payload": ("mass", "kg", (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)),
    "time_delay@shift": ("pure delay d", "s", (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05)),
    "time_delay@lag": ("lag d", "s", (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1)),
    "base_tilt": ("tilt", "rad", (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05)),
    "joint_elasticity": ("compliance 1/k", "rad/(N·m)", (1e-5, 2e-5, 5e-5, 1e-4, 2e-4, 5e-4, 1e-3, 3e-3)),
}
DETECTION_RATE = 0.9
ELASTIC_JOINTS = (1, 3, 5)  # 0-based: the Gen3's pitch joints 2, 4, 6


def effect_at(key: str, size: float, model: RobotModel, *, rng: np.random.Generator) -> tuple[str, dict]:
    """(effect name, effect in its physical form) of DETECTION_LADDERS key at `size`."""
    n = model.n
    name = key.split("@")[0]
    mask = np.zeros(n)
    mask[rng.choice(ELASTIC_JOINTS) if name == "joint_elasticity" and n == 7 else rng.integers(n)] = 1.0
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if name in ("coulomb_friction", "viscous_friction", "armature"):
        return name, {"delta": mask * size}
    if name == "stribeck_friction":
        return name, {"delta": mask * size, "vs": float(rng.choice(STRIBECK_VS))}
    if name == "torque_offset":
        return name, {"delta": mask * sign * size}
    if name == "load_friction":
        return name, {"mu": mask * size}
    if name == "torque_scale":
        return name, {"scale": 1.0 + mask * sign * size}
    if name == "joint_elasticity":
        return name, {"compliance": mask * size}
    if name == "payload":
        return name, {"mass_kg": size, "theta": payload_theta(model, size, rng)}
    if name == "time_delay":
        return name, ({"delay_s": size, "law": "lag"} if key.endswith("@lag") else {"delay_s": size})
    if name == "base_tilt":
        ang = rng.uniform(-1, 1, 2)
        return name, {"roll_pitch_rad": size * ang / np.abs(ang).max()}
    raise ValueError(key)


def _detection_case(job):
    """Is an effect of a given physical size named (and is anything else named)?"""

    model, seed, key, level, size, i = job
    rng = np.random.default_rng(
        [seed, list(DETECTION_LADDERS).index(key), int(round(1e4 * level)), int(round(1e9 * size)), i]
    )
    name, eff = effect_at(key, size, model, rng=rng)
    with single_threaded_blas():
        fit, check, truth = make_case(model, rng, [name], i % 2 == 0, fixed={name: eff}, noise_level=level)
        named = diagnose(model, fit, check).result["cause"]
    return {"found": name in named, "false": [e for e in named if e != name], "snr": truth["effects"][name]["snr"]}


def _ladder(job):
    """Walk one effect's ladder at one noise level: start in the middle, go down while the rate
    holds, up while it does not; the smallest size found in >= DETECTION_RATE of the cases."""
    model, seed, key, level, n_cases = job
    sizes = DETECTION_LADDERS[key][2]
    tried = {}

    def rate(k):
        if k not in tried:
            res = [_detection_case((model, seed, key, level, sizes[k], i)) for i in range(n_cases)]
            tried[k] = {
                "size": sizes[k],
                "found": sum(r["found"] for r in res),
                "cases": n_cases,
                "false": sum(bool(r["false"]) for r in res),
                "snr_median": float(np.median([r["snr"] for r in res])),
            }
        return tried[k]["found"] / n_cases

    k = len(sizes) // 2
    if rate(k) >= DETECTION_RATE:
        while k > 0 and rate(k - 1) >= DETECTION_RATE:
            k -= 1
        limit = k
    else:
        while k + 1 < len(sizes) and rate(k + 1) < DETECTION_RATE:
            k += 1
        limit = k + 1 if k + 1 < len(sizes) else None
    quantity, unit, _ = DETECTION_LADDERS[key]
    return {
        "effect": key,
        "quantity": quantity,
        "unit": unit,
        "noise_level": level,
        "limit": sizes[limit] if limit is not None else None,
        "snr_at_limit": tried[limit]["snr_median"] if limit is not None else None,
        "tried": [tried[k] for k in sorted(tried)],
    }


def detection_limits(
    model: RobotModel,
    *,
    noise_levels: Sequence[float] = (0.01, 0.03),
    n_cases: int = 10,
    seed: int = 0,
    workers: int = 1,
    keys: Sequence[str] | None = None,
    progress: Callable[[dict], None] | None = None,
) -> list[dict]:
    """Per effect (time_delay per law) and noise level (fraction of each joint's torque range):
    the smallest size of DETECTION_LADDERS named in >= 90 % of n_cases blind cases (single
    effect, random joint, random trajectories; half without accelerations)."""
    jobs = [(model, seed, key, level, n_cases) for key in (keys or DETECTION_LADDERS) for level in noise_levels]
    out = []
    for r in parallel_map(_ladder, jobs, workers):
        out.append(r)
        if progress:
            progress(r)
    return out


def detection_markdown(limits: list[dict]) -> str:
    levels = sorted({r["noise_level"] for r in limits})
    by = {(r["effect"], r["noise_level"]): r for r in limits}
    keys = list(dict.fromkeys(r["effect"] for r in limits))
    head = "| effect | quantity | " + " | ".join(f"found in ≥ 90 % at {100 * lv:g} % noise" for lv in levels) + " |"
    lines = [head, "|---|---|" + "---|" * len(levels)]
    for key in keys:
        r0 = by[(key, levels[0])]
        cells = []
        for lv in levels:
            r = by[(key, lv)]
            cells.append(
                "> largest tried" if r["limit"] is None else f"{r['limit']:g} {r['unit']} (SNR {r['snr_at_limit']:.2f})"
            )
        lines.append(f"| {key} | {r0['quantity']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
