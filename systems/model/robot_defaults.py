"""A scenario's robot-specific values: what the robot's parameter file declares in its `defaults:`
section, else what the rules below derive from the robot model (docs/own-robot.md, "Defaults").
A model file loaded alone (a diagnosis' corrected model) takes the `defaults:` of the parameter
file beside it that names it.

The scenario fields keep their names; an empty one is unset. fill_robot_defaults fills the unset
ones of a scenario: robot_from_scenario calls it, and so does the arm station with the robot it
is given, so a Scenario made in code resolves as a loaded one; the scenario loader goes through
robot_from_scenario too, or through fill_declared_defaults when the file declares every value.

Rules (a robot file without a value):
- q0_rad: the middle of the joint box (0 on a joint without both limits, kept inside the one it has).
- controller gains, from M_j = the largest diagonal entry of the mass matrix (armature included)
  over MASS_SAMPLES seeded configurations in the joint box (continuous joints over one turn), and
  the bandwidth w = BANDWIDTH_RAD_S: Kr = w / 2 (ARMOUR's position-error rate), pid_kp = M_j w^2,
  pid_ki = pid_kp * INTEGRAL_CORNER_RAD_S, pid_kd = 2 DAMPING_RATIO w M_j, adaptive_kd = w M_j.
  Gains are tuning, not guarantees: ARMOUR's tube and the planner's certificate hold for any Kr.
- planner.k_center_rad: 0; planner.k_range_rad: the joint's velocity limit x RANGE_TIME_S (the
  planner shrinks the box it certifies, so the range is a search box, not a promise).
- fourier.acceleration_limit_rad_s2: the velocity limit reached in ACCELERATION_TIME_S.
- initial_interval (the end-effector prior): never derived from the robot alone; a robot file
  declares one (the Gen3: Table II) or the scenario gives initial_interval.payload_mass_kg.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml
from safesysid.systems.config import Scenario, ScenarioError

if TYPE_CHECKING:
    from safesysid.systems.model.robot_model import RobotModel

GAINS = (
    "controller.Kr",
    "controller.pid_kp_Nm_rad",
    "controller.pid_ki_Nm_rad_s",
    "controller.pid_kd_Nms_rad",
    "controller.adaptive_kd_Nms_rad",
)
PER_JOINT = ("q0_rad", *GAINS, "planner.k_center_rad", "planner.k_range_rad", "fourier.acceleration_limit_rad_s2")
PRIOR = ("initial_interval.nominal", "initial_interval.lower", "initial_interval.upper")
FIELDS = PER_JOINT + PRIOR

BANDWIDTH_RAD_S = 10.0
DAMPING_RATIO = 0.9
INTEGRAL_CORNER_RAD_S = 1.0
RANGE_TIME_S = 0.05
ACCELERATION_TIME_S = 0.25
MASS_SAMPLES = 256


def _flatten(section: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in section.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _declaring_file(robot: RobotModel) -> tuple[dict | None, str]:
    """(document, path) of the parameter file whose `defaults:` apply: the robot's own, or for a
    model file loaded alone (a diagnosis' corrected model) the parameter YAML beside it that names
    it (models/kinova_gen3_params.yaml for models/kinova_gen3.urdf)."""
    if robot.extra.get("params_doc") is not None:
        return robot.extra["params_doc"], robot.extra.get("params_path") or robot.source
    model = Path(robot.source)
    for path in sorted(model.parent.glob("*.yaml")) if model.is_file() else ():
        try:
            doc = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError):
            continue
        if isinstance(doc, dict) and doc.get("urdf") == model.name:
            return doc, str(path)
    return None, robot.source


def _params_file(robot: RobotModel) -> str:
    return _declaring_file(robot)[1]


def declared_defaults(doc: dict | None, *, n: int, where: str) -> dict[str, list[float]]:
    """The `defaults:` section of a robot parameter file `doc` (of n joints), by field path ({}
    without one); ScenarioError naming the file `where` and the key for an unknown key or a wrong count."""
    section = (doc or {}).get("defaults") or {}
    if not isinstance(section, dict):
        raise ScenarioError(f"{where}: defaults: expected a mapping")
    declared = {}
    for key, value in _flatten(section).items():
        if key not in FIELDS:
            raise ScenarioError(f"{where}: defaults.{key}: unknown key (known: {', '.join(FIELDS)})")
        count = 10 if key in PRIOR else n
        try:
            values = [float(x) for x in value]
        except (TypeError, ValueError):
            values = []
        if len(values) != count:
            raise ScenarioError(f"{where}: defaults.{key}: needs {count} numbers")
        declared[key] = values
    return declared


def joint_box_middle(robot: RobotModel) -> np.ndarray:
    """The middle of each joint's limits; 0 (clipped into a one-sided limit) where one is infinite."""
    jp = robot.joint_params
    lo, hi = np.asarray(jp.position_lower, float), np.asarray(jp.position_upper, float)
    bounded = np.isfinite(lo) & np.isfinite(hi)
    return np.where(bounded, 0.5 * (np.where(bounded, lo, 0.0) + np.where(bounded, hi, 0.0)), np.clip(0.0, lo, hi))


def heaviest_inertia(robot: RobotModel) -> np.ndarray:
    """Per joint, the largest diagonal entry of M(q) (armature included) over MASS_SAMPLES
    seeded configurations in the joint box (limits clipped to one turn about 0)."""
    jp = robot.joint_params
    lo = np.clip(np.asarray(jp.position_lower, float), -np.pi, np.pi)
    hi = np.clip(np.asarray(jp.position_upper, float), -np.pi, np.pi)
    q = np.random.default_rng(0).uniform(lo, hi, (MASS_SAMPLES, robot.n))
    return np.diagonal(robot.mass_matrix(q), axis1=1, axis2=2).max(0)


def derived_defaults(robot: RobotModel, fields: Iterable[str] = PER_JOINT) -> dict[str, list[float]]:
    """The rules of the module docstring, for the per-joint `fields` asked (the prior has none)."""
    fields = [f for f in fields if f in PER_JOINT]
    speed = np.asarray(robot.joint_params.velocity_limit, float)
    if any(f in fields for f in ("planner.k_range_rad", "fourier.acceleration_limit_rad_s2")) and not (
        np.all(np.isfinite(speed)) and np.all(speed > 0)
    ):
        raise ScenarioError(
            f"{_params_file(robot)}: joints.velocity_limit_rad_s: finite limits > 0 needed "
            "to derive k ranges and acceleration limits"
        )
    w, n = BANDWIDTH_RAD_S, robot.n
    rules = {
        "q0_rad": lambda: joint_box_middle(robot),
        "controller.Kr": lambda: np.full(n, w / 2),
        "planner.k_center_rad": lambda: np.zeros(n),
        "planner.k_range_rad": lambda: speed * RANGE_TIME_S,
        "fourier.acceleration_limit_rad_s2": lambda: speed / ACCELERATION_TIME_S,
    }
    if any(f in fields for f in GAINS[1:]):
        inertia = heaviest_inertia(robot)
        rules |= {
            "controller.pid_kp_Nm_rad": lambda: inertia * w**2,
            "controller.pid_ki_Nm_rad_s": lambda: inertia * w**2 * INTEGRAL_CORNER_RAD_S,
            "controller.pid_kd_Nms_rad": lambda: 2 * DAMPING_RATIO * w * inertia,
            "controller.adaptive_kd_Nms_rad": lambda: w * inertia,
        }
    return {f: [float(x) for x in rules[f]()] for f in fields}


def robot_defaults(robot: RobotModel, fields: Iterable[str] = FIELDS) -> dict[str, list[float]]:
    """The robot's value of each of `fields`: declared in its file, else derived (a prior the
    file does not declare is left out)."""
    fields = list(fields)
    if not fields:
        return {}
    doc, where = _declaring_file(robot)
    declared = declared_defaults(doc, n=robot.n, where=where)
    values = {f: declared[f] for f in fields if f in declared}
    return values | derived_defaults(robot, [f for f in fields if f not in values])


def _section_and_name(scenario: Scenario, field: str):
    *path, name = field.split(".")
    obj = scenario
    for part in path:
        obj = getattr(obj, part)
    return obj, name


def field_value(scenario: Scenario, field: str) -> object:
    """The value of a dotted field path (e.g. "controller.Kr") of a scenario."""
    return getattr(*_section_and_name(scenario, field))


def unset_fields(scenario: Scenario, fields: Iterable[str] = FIELDS) -> list[str]:
    """Of `fields`, the robot-specific ones a scenario leaves empty (the prior only without a
    payload range, from which the scenario loader derives it)."""
    derived_prior = np.size(scenario.initial_interval.payload_mass_kg) > 0
    unset = [f for f in fields if np.size(field_value(scenario, f)) == 0]
    return [f for f in unset if not (derived_prior and f in PRIOR)]


def fill_robot_defaults(scenario: Scenario, robot: RobotModel, fields: Iterable[str] = FIELDS) -> list[str]:
    """Set each unset robot-specific field of `scenario` (in place; of `fields`) to the robot's
    value; returns the fields set. ScenarioError when the prior is unset and the robot's file
    declares none."""
    unset = unset_fields(scenario, fields)
    if not unset:
        return []
    values = robot_defaults(robot, unset)
    if any(f not in values for f in unset):
        raise ScenarioError(
            f"{scenario.source or '<scenario>'}: initial_interval: {_params_file(robot)} declares no prior "
            "(defaults.initial_interval); give initial_interval.payload_mass_kg (a prior derived from "
            "a payload range) or nominal, lower and upper"
        )
    _set(scenario, {f: values[f] for f in unset})
    return unset


def fill_declared_defaults(scenario: Scenario, doc: dict | None, *, where: str) -> bool:
    """fill_robot_defaults without the model, when the parameter file `doc` (`where`) declares
    every unset field (nothing set otherwise); True when nothing is left unset. The loader's fast
    path: reading the model file costs ~0.1 s a load."""
    try:
        n = len(doc["joints"]["names"])
    except (KeyError, TypeError):
        return False
    unset = unset_fields(scenario)
    declared = declared_defaults(doc, n=n, where=where)
    if any(f not in declared for f in unset):
        return False
    _set(scenario, {f: declared[f] for f in unset})
    return True


def _set(scenario: Scenario, values: dict[str, list[float]]) -> None:
    for field, value in values.items():
        section, name = _section_and_name(scenario, field)
        setattr(section, name, list(value))
