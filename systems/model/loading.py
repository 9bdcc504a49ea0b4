"""The RobotModel a scenario names (one source of truth for every system), corrected by a
diagnosis' corrected_model.yaml when the scenario says so, and the scenario's file paths."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from safesysid.systems.config import Robot, Scenario, ScenarioError
from safesysid.systems.model.corrections import CorrectionError, corrected_robot, read_correction
from safesysid.systems.model.robot_defaults import fill_robot_defaults
from safesysid.systems.model.robot_model import MODELS_DIR, ModelError, RobotModel, load_robot

if TYPE_CHECKING:
    from safesysid.systems.model.corrected_model import CorrectedModel


def resolve_path(text: str, base_dir: str | Path) -> Path:
    """`builtin:NAME` -> models/NAME; relative paths against the scenario's folder."""
    if text.startswith("builtin:"):
        return MODELS_DIR / text[len("builtin:") :]
    p = Path(text).expanduser()
    return p if p.is_absolute() else Path(base_dir) / p


def scenario_dir(s: Scenario) -> Path:
    return Path(s.source).parent


def robot_from_scenario(s: Scenario) -> RobotModel:
    """The RobotModel a scenario names (one source of truth for every system). The scenario's unset
    robot-specific fields are filled from it on the way (robot_defaults.fill_robot_defaults), so a
    Scenario built in code resolves as a loaded one does."""
    robot = _robot_of(s.robot, scenario_dir(s), s.source)
    fill_robot_defaults(s, robot)
    return robot


def _robot_of(robot: Robot, base: Path, where: str) -> RobotModel:
    """The RobotModel of a scenario's `robot` section (paths relative to `base`)."""
    if robot.corrected_model:
        try:
            corr = read_correction(resolve_path(robot.corrected_model, base))
            return corrected_robot(starting_robot(corr, robot.coulomb_smoothing_rad_s), corr)
        except CorrectionError as err:
            raise ScenarioError(f"{where}: robot.corrected_model: {err}") from err
    model = resolve_path(robot.model, base) if robot.model else None
    try:
        return load_robot(
            model_path=model,
            params_path=resolve_path(robot.params, base),
            coulomb_smoothing=robot.coulomb_smoothing_rad_s,
        )
    except ModelError as err:  # name the scenario and the field, not only the model file
        field = f"robot.model ({robot.model})" if robot.model else f"robot.params ({robot.params})"
        raise ScenarioError(f"{where}: {field}: {err}") from err


def starting_robot(corr: CorrectedModel, coulomb_smoothing: float = 0.0) -> RobotModel:
    """The model a diagnosis started from (a corrected model's `model`): a URDF/SDF (root welded,
    friction zero) or the robot of a scenario YAML, read from its `robot` section (the rest of
    that scenario does not change the robot; app/scenario.py validates the whole file)."""
    from pydrake.common.yaml import yaml_load_typed

    path = corr.model_path()
    if not path.is_file():
        raise CorrectionError(f"{corr.path}: model: file {corr.model!r} not found")
    if path.suffix.lower() not in (".yaml", ".yml"):
        return load_robot(model_path=path, coulomb_smoothing=coulomb_smoothing)
    import yaml

    try:
        section = (yaml.safe_load(path.read_text()) or {}).get("robot") or {}
        robot = yaml_load_typed(schema=Robot, data=yaml.safe_dump(section), defaults=Robot())
    except (yaml.YAMLError, RuntimeError, AttributeError) as err:
        raise CorrectionError(f"{path}: robot: not a scenario robot section ({err})") from err
    return _robot_of(robot, path.parent, str(path))
