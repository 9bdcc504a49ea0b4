"""`corrected_model.yaml`: the model a diagnosis started from plus every selected effect with its
fitted parameters, one schema, written by `safesysid diagnose` and read back by
`safesysid diagnose --model corrected_model.yaml --check X.csv` (frozen scoring) and by the
consumers of a corrected model (scenario loading, the simulated arm, `sysid --model`).

Schema (a stable contract: add keys, never rename or drop):
    model: path of the starting URDF/SDF/scenario YAML, as given to `diagnose`
    model_resolved: the same path, absolute
    effects:                         # most explanatory first
      - name: one of diagnosis.EFFECTS
        joints: [1-based joints where the effect matters]
        params: {...}                # exactly diagnosis.effect_params (units in the key names), plus
                                     # time_delay.time_law: lag | shift (machine-readable law)
        intervals: {key: [lo, hi]}   # optional: statistical 90 % intervals of params values (per-joint
                                     # values: [[lo per joint], [hi per joint]]; null: no information),
                                     # diagnosis/intervals.py; time_delay's key is delay_s. Not
                                     # Algorithm 1's provable interval.
    scoring:                         # what a frozen scoring needs besides the effects
      residual_form: inverse_dynamics | momentum
      window_s: momentum-form window
      saturation: {top_speed_rad_s: [n], level, band_rad_s, min_duration_s}
                                     # speed-saturation rule frozen on the fit logs
    fitted_on: [fit logs]            # information only

Every parameter applies to all joints of the model (per-joint lists have n entries); `joints`
only says where the effect was found to matter.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# The effect library's names (systems/diagnosis/effects.py implements each).
EFFECT_NAMES = (
    "coulomb_friction",
    "viscous_friction",
    "stribeck_friction",
    "load_friction",
    "armature",
    "torque_offset",
    "torque_scale",
    "payload",
    "time_delay",
    "base_tilt",
    "joint_elasticity",
)
TIME_LAWS = ("lag", "shift")  # first-order lag of the model side, pure delay
# Parameter keys a frozen model needs per effect (the others are derived, for people), and
# whether each is a per-joint list (True), a fixed-length list (int) or a number (None).
REQUIRED = {
    "coulomb_friction": {"delta_Fc_Nm": True},
    "viscous_friction": {"delta_Fv_Nms_rad": True},
    "stribeck_friction": {"Fs_Nm": True, "vs_rad_s": None},
    "load_friction": {"mu": True},
    "armature": {"delta_Ia_kgm2": True},
    "torque_offset": {"offset_Nm": True},
    "torque_scale": {"scale": True},
    "payload": {"theta_delta": 10},
    "time_delay": {"delay_s": None, "time_law": "law"},
    "base_tilt": {"gravity_xy_over_g": 2},
    "joint_elasticity": {"compliance_rad_per_Nm": True},
}
SCORING_FORMS = ("inverse_dynamics", "momentum")


class CorrectedModelError(ValueError):
    """Bad corrected_model.yaml; the message names the file and the field."""


@dataclass
class CorrectedEffect:
    name: str
    joints: list[int]  # 1-based
    params: dict[str, Any]  # diagnosis.effect_params(...) (+ time_law for time_delay)
    intervals: dict[str, list] = field(default_factory=dict)  # statistical 90 % intervals (diagnosis/intervals.py)


@dataclass
class Saturation:
    """Speed-saturation rule frozen on the fit logs (design.velocity_saturation)."""

    top_speed_rad_s: list[float]
    level: float
    band_rad_s: float
    min_duration_s: float


@dataclass
class Scoring:
    residual_form: str = "inverse_dynamics"
    window_s: float = 0.1
    saturation: Saturation | None = None


@dataclass
class CorrectedModel:
    model: str  # as given to diagnose
    effects: list[CorrectedEffect] = field(default_factory=list)
    scoring: Scoring = field(default_factory=Scoring)
    model_resolved: str = ""
    fitted_on: list[str] = field(default_factory=list)
    path: str = ""  # the file it was read from

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.effects]

    def model_path(self) -> Path:
        """The starting model file: model_resolved when it exists, else `model` relative to
        this file's folder, else `model` as written."""
        resolved = Path(self.model_resolved) if self.model_resolved else None
        if resolved is not None and not resolved.is_absolute() and self.path:
            resolved = Path(self.path).parent / resolved  # written relative to this file's folder
        candidates = [resolved] if resolved is not None else []
        if self.path and not Path(self.model).is_absolute():
            candidates.append(Path(self.path).parent / self.model)
        candidates.append(Path(self.model))
        return next((p for p in candidates if p.is_file()), candidates[-1])

    def check_joints(self, n: int) -> None:
        """Per-joint lists must have the model's n entries; raise naming file and field."""
        for k, e in enumerate(self.effects):
            for key, kind in REQUIRED[e.name].items():
                if kind is True and len(e.params[key]) != n:
                    raise CorrectedModelError(
                        f"{self.path or 'corrected model'}: effects[{k}].params.{key}: "
                        f"{len(e.params[key])} values for a model with {n} joints"
                    )
            if any(j > n for j in e.joints):
                raise CorrectedModelError(
                    f"{self.path or 'corrected model'}: effects[{k}].joints: joint > {n} (the model has {n} joints)"
                )
        sat = self.scoring.saturation
        if sat is not None and len(sat.top_speed_rad_s) != n:
            raise CorrectedModelError(
                f"{self.path or 'corrected model'}: scoring.saturation.top_speed_rad_s: "
                f"{len(sat.top_speed_rad_s)} values for a model with {n} joints"
            )

    def to_doc(self) -> dict:
        doc = {
            "model": self.model,
            "model_resolved": self.model_resolved,
            "effects": [_effect_doc(e) for e in self.effects],
            "scoring": {"residual_form": self.scoring.residual_form, "window_s": float(self.scoring.window_s)},
        }
        sat = self.scoring.saturation
        if sat is not None:
            doc["scoring"]["saturation"] = {
                "top_speed_rad_s": [float(x) for x in sat.top_speed_rad_s],
                "level": float(sat.level),
                "band_rad_s": float(sat.band_rad_s),
                "min_duration_s": float(sat.min_duration_s),
            }
        if self.fitted_on:
            doc["fitted_on"] = [str(p) for p in self.fitted_on]
        return doc


def _effect_doc(e: CorrectedEffect) -> dict:
    doc = {"name": e.name, "joints": [int(j) for j in e.joints], "params": _plain(e.params)}
    if e.intervals:
        doc["intervals"] = _plain(e.intervals)
    return doc


def _plain(x):
    """YAML-safe copy (numpy scalars/arrays to floats and lists)."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if hasattr(x, "tolist"):
        return _plain(x.tolist())
    if isinstance(x, bool) or x is None or isinstance(x, str):
        return x
    if isinstance(x, int):
        return x
    return float(x)


def write_corrected_model(path: str | Path, corrected: CorrectedModel, header: str = "") -> Path:
    """Write `corrected` (CorrectedModel) as YAML; floats round-trip exactly (repr)."""
    import yaml

    doc = corrected.to_doc()
    if doc["model_resolved"] and Path(doc["model_resolved"]).is_absolute():
        # relative to the file's folder, so a diagnosis folder can be moved or shared with its model
        doc["model_resolved"] = os.path.relpath(doc["model_resolved"], Path(path).resolve().parent)
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120)
    Path(path).write_text(header + text)
    return Path(path)


def is_corrected_model_file(path: str | Path) -> bool:
    """True for a YAML whose top level has both `model` and `effects` (a scenario has neither)."""
    import yaml

    p = Path(path)
    if p.suffix.lower() not in (".yaml", ".yml") or not p.is_file():
        return False
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError:
        return False
    return isinstance(doc, dict) and "model" in doc and "effects" in doc


def read_corrected_model(path: str | Path) -> CorrectedModel:
    """CorrectedModel from a corrected_model.yaml; CorrectedModelError (one line naming file and
    field) on anything missing or malformed. Joint counts are checked against a model with
    CorrectedModel.check_joints(n) once the model is loaded."""
    where = str(path)
    doc = _load_yaml(Path(path), where)

    def bad(field_name, msg):
        return CorrectedModelError(f"{where}: {field_name}: {msg}")

    if not isinstance(doc, dict):
        raise bad("top level", "expected a mapping with `model` and `effects`")
    model = doc.get("model")
    if not isinstance(model, str) or not model:
        raise bad("model", "missing (path of the starting URDF/SDF/scenario)")
    effects_doc = doc.get("effects")
    if not isinstance(effects_doc, list):
        raise bad("effects", "missing or not a list")
    effects = []
    for k, e in enumerate(effects_doc):
        f = f"effects[{k}]"
        name, joints, params = _read_effect(e, f, bad)
        if name in [x.name for x in effects]:
            raise bad(f"{f}.name", f"{name} given twice")
        effects.append(
            CorrectedEffect(name, list(joints), dict(params), _read_intervals(e.get("intervals", {}), f, bad))
        )
    scoring = _read_scoring(doc.get("scoring", {}), bad)
    fitted_on = doc.get("fitted_on", [])
    resolved = doc.get("model_resolved", "") or ""
    if not isinstance(resolved, str):
        raise bad("model_resolved", "expected a path")
    return CorrectedModel(
        model, effects, scoring, resolved, list(fitted_on) if isinstance(fitted_on, list) else [], str(path)
    )


def _load_yaml(p, where):
    import yaml

    try:
        return yaml.safe_load(p.read_text())
    except OSError as err:
        raise CorrectedModelError(f"{where}: cannot read ({err.strerror})") from err
    except yaml.YAMLError as err:
        line = getattr(getattr(err, "problem_mark", None), "line", None)
        raise CorrectedModelError(
            f"{where}: not valid YAML" + (f" (line {line + 1})" if line is not None else "")
        ) from err


def _read_effect(e, f, bad):
    """(name, joints, params) of the effect entry `e` at field `f`, checked against REQUIRED."""
    if not isinstance(e, dict):
        raise bad(f, "expected a mapping {name, joints, params}")
    name = e.get("name")
    if name not in EFFECT_NAMES:
        raise bad(f"{f}.name", f"unknown effect {name!r} (known: {', '.join(EFFECT_NAMES)})")
    joints = e.get("joints", [])
    if not isinstance(joints, list) or not all(_is_joint_number(j) for j in joints):
        raise bad(f"{f}.joints", "expected a list of 1-based joint numbers")
    params = e.get("params")
    if not isinstance(params, dict):
        raise bad(f"{f}.params", "missing or not a mapping")
    if name == "time_delay" and "time_law" not in params and isinstance(params.get("law"), str):
        # Files written before `time_law` existed name the law in prose only.
        params = {**params, "time_law": "lag" if params["law"].startswith("first-order") else "shift"}
    for key, kind in REQUIRED[name].items():
        if key not in params:
            raise bad(f"{f}.params.{key}", "missing")
        _check_param(params[key], kind, f"{f}.params.{key}", bad)
    return name, joints, params


def _check_param(val, kind, field_name, bad):
    """kind (REQUIRED): "law" a time law, None a finite number, True a list of them, an int a list
    of that many."""
    if kind == "law":
        if val not in TIME_LAWS:
            raise bad(field_name, f"expected one of {', '.join(TIME_LAWS)}, got {val!r}")
    elif kind is None:
        if not _finite(val):
            raise bad(field_name, f"expected a finite number, got {val!r}")
    else:
        if not isinstance(val, list) or not all(_finite(x) for x in val):
            raise bad(field_name, "expected a list of finite numbers")
        if kind is not True and len(val) != kind:
            raise bad(field_name, f"expected {kind} values, got {len(val)}")


def _read_intervals(doc, f, bad):
    """An effect's optional `intervals`: {key: [lo, hi]}, lo/hi numbers, null or lists of them."""
    if not isinstance(doc, dict):
        raise bad(f"{f}.intervals", "expected a mapping {key: [lo, hi]}")
    for key, pair in doc.items():
        bound = lambda x: x is None or _finite(x)  # noqa: E731 (null: no information)
        ok = isinstance(pair, list) and len(pair) == 2
        ok = ok and all(bound(x) or (isinstance(x, list) and all(bound(y) for y in x)) for x in pair)
        if not ok:
            raise bad(f"{f}.intervals.{key}", "expected [lo, hi] (numbers, null or per-joint lists)")
    return dict(doc)


def _is_joint_number(j):
    return isinstance(j, int) and not isinstance(j, bool) and j >= 1


def _finite(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _read_scoring(doc, bad):
    if not isinstance(doc, dict):
        raise bad("scoring", "expected a mapping")
    form = doc.get("residual_form", "inverse_dynamics")
    if form not in SCORING_FORMS:
        raise bad("scoring.residual_form", f"expected one of {', '.join(SCORING_FORMS)}, got {form!r}")
    window = doc.get("window_s", 0.1)
    if not _finite(window) or window <= 0:
        raise bad("scoring.window_s", f"expected a positive number, got {window!r}")
    sat_doc = doc.get("saturation")
    sat = None
    if sat_doc is not None:
        if not isinstance(sat_doc, dict):
            raise bad("scoring.saturation", "expected a mapping")
        vals = {}
        for key in ("level", "band_rad_s", "min_duration_s"):
            if not _finite(sat_doc.get(key)) or sat_doc[key] < 0:
                raise bad(f"scoring.saturation.{key}", f"expected a non-negative number, got {sat_doc.get(key)!r}")
            vals[key] = float(sat_doc[key])
        top = sat_doc.get("top_speed_rad_s")
        if not isinstance(top, list) or not all(_finite(x) and x >= 0 for x in top):
            raise bad("scoring.saturation.top_speed_rad_s", "expected a list of non-negative numbers")
        sat = Saturation([float(x) for x in top], **vals)
    return Scoring(form, float(window), sat)


def group_params(effects: Sequence[CorrectedEffect]) -> dict[str, np.ndarray]:
    """{column group: parameter array} of CorrectedEffects, the inverse of effects.effect_params
    (the form the diagnosis' residuals take)."""
    out = {}
    for e in effects:
        p = e.params
        if e.name == "stribeck_friction":
            out[f"stribeck_friction@{float(p['vs_rad_s'])}"] = np.array(p["Fs_Nm"], float)
        elif e.name == "time_delay":
            out[f"time_delay@{p['time_law']}"] = np.array([float(p["delay_s"])])
        elif e.name == "torque_scale":
            out[e.name] = np.array(p["scale"], float) - 1.0
        else:
            key = next(iter(REQUIRED[e.name]))
            out[e.name] = np.array(p[key], float)
    return out
