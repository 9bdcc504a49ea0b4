"""Scenario loader: YAML layers read with Drake's yaml_load_typed into the schema of
systems/config.py, checked field by field with errors naming file and key.
"""

import dataclasses as dc
import typing
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import yaml
from safesysid.systems.config import (
    MAX_CONTROL_STEP_S,
    Scenario,
    ScenarioError,
    task_enabled,
)
from safesysid.systems.model.loading import resolve_path, robot_from_scenario, scenario_dir
from safesysid.systems.model.robot_defaults import fill_declared_defaults

if typing.TYPE_CHECKING:
    from safesysid.systems.model.corrected_model import CorrectedModel

SCENARIOS_DIR = Path(__file__).resolve().parent.parent / "scenarios"
List = list


def choices_of(cls: type = Scenario, prefix: str = "") -> dict[str, tuple[str, ...]]:
    """{dotted field path: its allowed values} of every field declared with systems/config.py
    one_of, nested sections included (lists of sections have none)."""
    found = {}
    hints = typing.get_type_hints(cls)
    for f in dc.fields(cls):
        if "choices" in f.metadata:
            found[f"{prefix}{f.name}"] = f.metadata["choices"]
        elif dc.is_dataclass(hints[f.name]):
            found.update(choices_of(hints[f.name], f"{prefix}{f.name}."))
    return found


def _check_section(value, schema, path, errors):
    """A mapping against a section's dataclass: known keys, each checked against its field's type."""
    if not isinstance(value, dict):
        errors.append(f"{path or 'top level'}: expected a mapping")
        return
    fields = {f.name: f for f in dc.fields(schema) if f.name != "source"}
    for key, item in value.items():
        sub = f"{path}.{key}" if path else str(key)
        if key not in fields:
            errors.append(f"{sub}: unknown key (known: {', '.join(fields)})")
        else:
            _check(item, typing.get_type_hints(schema)[key], sub, errors)


def _check(value, schema, path, errors):
    """Walk raw YAML against the dataclass schema, collecting 'key.path: problem' strings."""
    origin = typing.get_origin(schema)
    if dc.is_dataclass(schema):
        _check_section(value, schema, path, errors)
    elif origin in (list, List):
        if not isinstance(value, list):
            errors.append(f"{path}: expected a list")
            return
        (inner,) = typing.get_args(schema)
        for k, item in enumerate(value):
            _check(item, inner, f"{path}[{k}]", errors)
    elif origin is typing.Union:
        inner = [a for a in typing.get_args(schema) if a is not type(None)][0]
        if value is not None:
            _check(value, inner, path, errors)
    elif schema in _SCALARS:
        accepts, expected = _SCALARS[schema]
        if not accepts(value):
            errors.append(f"{path}: expected {expected}, got {value!r}")


# The scalar types of the schema: (accepts a YAML value, what the error says was expected).
_SCALARS = {
    float: (lambda v: not isinstance(v, bool) and isinstance(v, (int, float)), "a number"),
    int: (lambda v: not isinstance(v, bool) and isinstance(v, int), "an integer"),
    str: (lambda v: isinstance(v, str), "a string"),
    bool: (lambda v: isinstance(v, bool), "true/false"),
}


def _params_doc(s: Scenario) -> dict | None:
    """The robot's parameter file, read (None when it cannot tell: a corrected model, or a file
    the robot loader will reject with its own message)."""
    if s.robot.corrected_model:
        return None
    try:
        return yaml.safe_load(resolve_path(s.robot.params, scenario_dir(s)).read_text()) or {}
    except (OSError, yaml.YAMLError):
        return None


def _joint_count(s: Scenario) -> int:
    """The joint count the robot's parameter file names (0 when it cannot tell)."""
    try:
        return len(_params_doc(s)["joints"]["names"])
    except (KeyError, TypeError):
        return 0


def _validate(s: Scenario, where):
    def need(cond, field, msg):
        if not cond:
            raise ScenarioError(f"{where}: {field}: {msg}")

    for key, allowed in choices_of().items():
        obj = s
        for part in key.split("."):
            obj = getattr(obj, part)
        need(obj in allowed, key, f"{obj!r} is not one of {', '.join(allowed)}")
    joints = _joint_count(s)
    need(
        len(s.q0_rad) == joints if joints else len(s.q0_rad) > 0,
        "q0_rad",
        f"must list one angle per joint of the robot ({joints or 'its joint count'}), got {len(s.q0_rad)}",
    )
    for k, ob in enumerate(s.obstacles):
        _validate_obstacle(ob, f"obstacles[{k}]", need)
    ii = s.initial_interval
    for name in ("nominal", "lower", "upper"):
        need(len(getattr(ii, name)) == 10, f"initial_interval.{name}", "needs 10 values")
    need(
        np.all(np.array(ii.lower) <= np.array(ii.nominal)) and np.all(np.array(ii.nominal) <= np.array(ii.upper)),
        "initial_interval",
        "needs lower <= nominal <= upper",
    )
    _validate_plant(s, need)
    _validate_estimator(s, need)
    _validate_planner(s, need)
    _validate_fourier(s, need)
    for field, text in (("robot.params", s.robot.params), ("payload.dumbbells_file", s.payload.dumbbells_file)):
        need(resolve_path(text, scenario_dir(s)).is_file(), field, f"file {text!r} not found")
    if s.robot.model:
        need(resolve_path(s.robot.model, scenario_dir(s)).is_file(), "robot.model", f"file {s.robot.model!r} not found")
    _validate_task(s, need)
    _validate_faults(s, need)
    _validate_arm_and_payload(s, need)


def _validate_plant(s: Scenario, need):
    # The tube's invariance is argued and measured for a controller step of at most 1 ms
    # (systems/controller/armour.py "Sampling"; docs/guarantees.md).
    need(
        0 < s.plant.time_step_s <= MAX_CONTROL_STEP_S,
        "plant.time_step_s",
        f"must be in (0, {MAX_CONTROL_STEP_S}] s (the tracking guarantee assumes a >= 1 kHz controller)",
    )
    need(s.plant.effects.time_delay_s >= 0, "plant.effects.time_delay_s", "must be >= 0")
    need(s.plant.effects.torque_sensor_lag_s >= 0, "plant.effects.torque_sensor_lag_s", "must be >= 0")
    eff = s.plant.effects
    need(eff.torque_sensor_delay_s >= 0, "plant.effects.torque_sensor_delay_s", "must be >= 0")
    need(all(0 <= mu < 1 for mu in eff.load_friction_mu), "plant.effects.load_friction_mu", "values must be in [0, 1)")
    need(all(fs >= 0 for fs in eff.stribeck_friction_Nm), "plant.effects.stribeck_friction_Nm", "values must be >= 0")
    need(eff.stribeck_velocity_rad_s > 0, "plant.effects.stribeck_velocity_rad_s", "must be > 0")
    need(eff.velocity_noise_rad_s >= 0, "plant.effects.velocity_noise_rad_s", "must be >= 0")


def _validate_estimator(s: Scenario, need):
    need(s.estimator.horizon_s > 0, "estimator.horizon_s", "must be > 0")
    need(s.estimator.quadrature_safety >= 2, "estimator.quadrature_safety", "must be >= 2")
    need(s.estimator.hold_period_s >= 0, "estimator.hold_period_s", "must be >= 0")
    need(s.estimator.torque_rate_limit_Nm_s > 0, "estimator.torque_rate_limit_Nm_s", "must be > 0")
    acc = s.estimator.acceleration_bound_rad_s2
    need(len(acc) in (0, 1, len(s.q0_rad)), "estimator.acceleration_bound_rad_s2", "must be one value or one per joint")
    need(all(a > 0 for a in acc), "estimator.acceleration_bound_rad_s2", "must be > 0")
    lag = s.estimator.torque_lag_s
    if isinstance(lag, list):
        need(len(lag) == 2, "estimator.torque_lag_s", "must be one number or [lo, hi]")
        need(0 <= lag[0] <= lag[1], "estimator.torque_lag_s", f"[lo, hi] needs 0 <= lo <= hi, got {lag}")
    else:
        need(lag >= 0, "estimator.torque_lag_s", "must be >= 0")
    for key in ("torque_lag_s", "torque_delay_s"):
        need(
            not np.any(getattr(s.estimator, key)) or s.estimator.torque_signal == "held",
            f"estimator.{key}",
            "needs estimator.torque_signal: held (the time law of a held torque is undone exactly)",
        )


def _validate_planner(s: Scenario, need):
    """The payload's bounding volume, the noise and the planner's settings."""
    vol = s.payload.bounding_volume
    for key in ("centre_m", "half_extent_m", "rpy_rad"):
        need(len(getattr(vol, key)) == 3, f"payload.bounding_volume.{key}", "needs 3 values")
    need(vol.shape == "none" or min(vol.half_extent_m) > 0, "payload.bounding_volume.half_extent_m", "must be > 0")
    for key, value in dc.asdict(s.noise.theta_r_floor).items():
        need(value >= 0, f"noise.theta_r_floor.{key}", "must be >= 0")
    need(s.planner.duration_s > 0, "planner.duration_s", "must be > 0")
    need(0 < s.planner.replan_period_s <= s.planner.duration_s, "planner.replan_period_s", "must be in (0, duration_s]")
    need(0 < s.planner.refinement_scale <= 1, "planner.refinement_scale", "must be in (0, 1]")
    need(s.task.max_time_scale >= 1, "task.max_time_scale", "must be >= 1 (1: never slower)")
    need(s.task.time_scale_step > 0, "task.time_scale_step", "must be > 0")
    need(
        not s.planner.continuation or s.planner.point_refinement,
        "planner.continuation",
        "needs planner.point_refinement: true (it is a condition on the refined point)",
    )
    need(s.noise.torque_ratio >= 0 and s.noise.declared_torque_ratio >= 0, "noise", "ratios must be >= 0")
    need(
        s.planner.exciting_weighting != "noise" or s.noise.declared_torque_floor_Nm > 0,
        "planner.exciting_weighting",
        "noise needs noise.declared_torque_floor_Nm > 0 (a row with zero torque would weigh infinitely)",
    )


def _validate_fourier(s: Scenario, need):
    f = s.fourier
    need(f.period_s > 0, "fourier.period_s", "must be > 0")
    need(f.num_harmonics >= 2, "fourier.num_harmonics", "must be >= 2 (rest at both ends uses one harmonic)")
    acc = f.acceleration_limit_rad_s2
    need(len(acc) == len(s.q0_rad) and min(acc) > 0, "fourier.acceleration_limit_rad_s2", "one value > 0 per joint")
    need(f.num_cost_samples >= 2 and f.max_iterations >= 0, "fourier", "num_cost_samples >= 2, max_iterations >= 0")


def _validate_arm_and_payload(s: Scenario, need):
    for key in ("watchdog_ms", "status_timeout_ms", "gripper_timeout_ms", "plan_lead_ms"):
        need(getattr(s.arm, key) > 0, f"arm.{key}", "must be > 0")
    need(s.arm.lcm_url.startswith(("udpm://", "memq://")), "arm.lcm_url", "must be an LCM url (udpm://... or memq://)")
    step, h, period = s.arm.run_step_ms * 1e-3, s.plant.time_step_s, s.planner.replan_period_s
    multiple = lambda a, b: abs(a / b - round(a / b)) < 1e-6  # noqa: E731
    need(
        step > 0 and multiple(step, h) and multiple(period, step),
        "arm.run_step_ms",
        "must be a multiple of plant.time_step_s that divides planner.replan_period_s",
    )
    if s.payload.dumbbell.lower() != "none":
        from safesysid.systems.model.payload import load_dumbbells

        names = list(load_dumbbells(resolve_path(s.payload.dumbbells_file, scenario_dir(s))))
        need(
            s.payload.dumbbell in names,
            "payload.dumbbell",
            f"{s.payload.dumbbell!r} is not one of none, {', '.join(names)}",
        )


def _validate_task(s: Scenario, need):
    t = s.task
    need(len(t.goal_q_rad) in (0, len(s.q0_rad)), "task.goal_q_rad", f"needs {len(s.q0_rad)} angles or none")
    need(len(t.place_xyz_m) in (0, 3), "task.place_xyz_m", "needs 3 values or none")
    need(not (t.goal_q_rad and t.place_xyz_m), "task", "give goal_q_rad or place_xyz_m, not both")
    names = [ob.name for ob in s.obstacles]
    need(
        not t.platform or t.platform in names,
        "task.platform",
        f"{t.platform!r} is not an obstacle name ({', '.join(names) or 'none'})",
    )
    need(t.release_height_m >= 0, "task.release_height_m", "must be >= 0")
    need(t.placement_tolerance_m > 0, "task.placement_tolerance_m", "must be > 0")
    need(t.return_duration_s > 0, "task.return_duration_s", "must be > 0")
    need(t.settle_time_s >= 0, "task.settle_time_s", "must be >= 0")
    need(t.duration_s > 0, "task.duration_s", "must be > 0")
    need(t.num_pieces >= 1, "task.num_pieces", "must be >= 1")
    need(t.collision_samples >= 2, "task.collision_samples", "must be >= 2")
    need(t.torque_samples >= 2, "task.torque_samples", "must be >= 2")
    need(0 <= t.torque_margin_ratio < 1, "task.torque_margin_ratio", "must be in [0, 1)")
    need(t.max_iterations >= 1, "task.max_iterations", "must be >= 1")
    need(t.max_solve_time_s > 0, "task.max_solve_time_s", "must be > 0")
    if task_enabled(s):
        from safesysid.systems.model.payload import load_dumbbells

        names = list(load_dumbbells(resolve_path(s.payload.dumbbells_file, scenario_dir(s))))
        need(t.payload_model in names, "task.payload_model", f"{t.payload_model!r} is not one of {', '.join(names)}")
        for k, name in enumerate(t.stack_on):
            need(name in names, f"task.stack_on[{k}]", f"{name!r} is not one of {', '.join(names)}")
    need(not t.stack_on or t.platform, "task.stack_on", "needs task.platform (the stack stands on it)")


def _validate_faults(s: Scenario, need):
    f = s.faults
    for key in (
        "torque_spike_magnitude_Nm",
        "torque_dropout_start_s",
        "torque_dropout_duration_s",
        "payload_extra_mass_kg",
        "velocity_clip_rad_s",
    ):
        need(getattr(f, key) >= 0, f"faults.{key}", "must be >= 0")
    for key in ("torque_spike", "sample_drop", "sample_duplicate", "sample_reorder", "sample_nan"):
        rate = getattr(f, f"{key}_rate_per_s")
        need(0 <= rate * s.plant.time_step_s <= 1, f"faults.{key}_rate_per_s", "must be in [0, 1 / plant.time_step_s]")
    n = len(s.q0_rad)
    need(all(1 <= j <= n for j in f.torque_spike_joints), "faults.torque_spike_joints", f"joints are 1..{n}")
    need(all(k >= 0 for k in f.planner_failure_calls), "faults.planner_failure_calls", "must be >= 0")
    for k, ob in enumerate(f.appearing_obstacles):
        need(ob.t_s >= 0, f"faults.appearing_obstacles[{k}].t_s", "must be >= 0")
        _validate_obstacle(ob, f"faults.appearing_obstacles[{k}]", need)


def _validate_obstacle(ob, field, need):
    need(len(ob.xyz_m) == 3, f"{field}.xyz_m", "needs 3 values")
    need(len(ob.rpy_rad) == 3, f"{field}.rpy_rad", "needs 3 values")
    need(len(ob.size_m) == 3 and min(ob.size_m) > 0, f"{field}.size_m", "needs 3 positive values")


def load_scenario(
    path: str | Path | None = None,
    text: str | None = None,
    overrides: str | dict | Sequence[str | dict] | None = None,
) -> Scenario:
    """Scenario from layers, the Drake way (examples/hardware_sim): the schema's defaults, then
    the YAML file `path` (or the YAML `text`), then each override, each layer read with
    yaml_load_typed(defaults=previous) so that it changes only the keys it names (a deep merge;
    a list is replaced whole). `overrides`: a mapping or YAML text, or a list of them applied in
    order (the CLI's --scenario-text). Raises ScenarioError naming the layer (file) and the key."""
    where = str(path) if path is not None else "<built-in defaults>"
    if path is not None:
        try:
            text = Path(path).read_text()
        except OSError as err:
            raise ScenarioError(f"{path}: cannot read scenario ({err.strerror})") from err
    if overrides is None:
        overrides = []
    elif isinstance(overrides, (str, dict)):
        overrides = [overrides]
    scenario = _read_layer(Scenario(), text, where)
    for k, layer in enumerate(overrides):
        scenario = _read_layer(scenario, layer, "--scenario-text" if len(overrides) == 1 else f"--scenario-text[{k}]")
    scenario.source = str(Path(path).resolve()) if path is not None else str(SCENARIOS_DIR / "defaults")
    _apply_corrected_model(scenario, _given_keys([text, *overrides]), where)
    label = where if path is not None else str(SCENARIOS_DIR / "defaults.yaml")
    label = f"{label} with --scenario-text" if overrides else label
    _resolve_robot(scenario, _given_keys([text, *overrides]), label)
    _validate(scenario, label)
    _stack_on_platform(scenario)
    return scenario


def _resolve_robot(s: Scenario, given, where) -> None:
    """The robot's values of the fields the layers left unset (systems/model/robot_defaults.py,
    through robot_from_scenario) and a prior derived from a payload range; _validate checks the
    result. A robot file that is not there is named first, before anything reads it."""
    for field, text in (("robot.params", s.robot.params), ("robot.model", s.robot.model)):
        if text and not s.robot.corrected_model and not resolve_path(text, scenario_dir(s)).is_file():
            raise ScenarioError(f"{where}: {field}: file {text!r} not found")
    where_params = str(resolve_path(s.robot.params, scenario_dir(s)))
    if s.robot.model or not fill_declared_defaults(s, _params_doc(s), where=where_params):
        robot_from_scenario(s)  # fills what the file does not declare from the model
    _derive_prior(s, given, where)


def _derive_prior(s: Scenario, given, where) -> None:
    """initial_interval.payload_mass_kg set: nominal/lower/upper from the robot's end-effector body
    and the declared payload range (systems/estimation/prior.py), written into the scenario."""
    ii = s.initial_interval
    if not ii.payload_mass_kg:
        return
    from safesysid.systems.estimation.prior import payload_range_prior

    stated = [k for k in ("nominal", "lower", "upper") if k in (given.get("initial_interval") or {})]
    checks = (
        (not stated, f"{', '.join(stated)}: not with payload_mass_kg (the prior is derived from it)"),
        (
            len(ii.payload_mass_kg) == 2 and 0 <= ii.payload_mass_kg[0] <= ii.payload_mass_kg[1],
            "payload_mass_kg: needs [lo, hi] with 0 <= lo <= hi",
        ),
        (len(ii.payload_centre_m) in (0, 3), "payload_centre_m: needs 3 values or none (the grasp point)"),
        (
            len(ii.payload_half_extent_m) == 3 and min(ii.payload_half_extent_m) >= 0,
            "payload_half_extent_m: needs 3 values >= 0",
        ),
    )
    for ok, msg in checks:
        if not ok:
            raise ScenarioError(f"{where}: initial_interval.{msg}")
    robot = robot_from_scenario(s)
    centre = ii.payload_centre_m or robot.extra["grasp_point"]
    nominal, lower, upper = payload_range_prior(
        robot.theta_e, ii.payload_mass_kg, centre_m=centre, half_extent_m=ii.payload_half_extent_m
    )
    ii.nominal, ii.lower, ii.upper = ([float(x) for x in v] for v in (nominal, lower, upper))


def _stack_on_platform(s: Scenario) -> None:
    """task.stack_on: the placed dumbbells become obstacle boxes on the platform (once, at load)
    and the payload's platform is the top one; stack_on is cleared so the result loads as is."""
    if not s.task.stack_on:
        return
    from safesysid.systems.model.payload import load_dumbbells
    from safesysid.systems.task.phase import stack_boxes

    bells = load_dumbbells(resolve_path(s.payload.dumbbells_file, scenario_dir(s)))
    platform = next(ob for ob in s.obstacles if ob.name == s.task.platform)
    boxes = stack_boxes(platform, [bells[name] for name in s.task.stack_on])
    s.obstacles = [*s.obstacles, *boxes]
    s.task = dc.replace(s.task, platform=boxes[-1].name, stack_on=[])


def _given_keys(layers):
    """The keys the layers set, deep-merged (a later layer wins): what the user wrote."""

    def merge(into, layer):
        for key, value in layer.items():
            if isinstance(value, dict) and isinstance(into.get(key), dict):
                merge(into[key], value)
            else:
                into[key] = value
        return into

    given = {}
    for layer in layers:
        raw = yaml.safe_load(layer) if isinstance(layer, str) else layer
        if isinstance(raw, dict):
            merge(given, raw)
    return given


def _apply_corrected_model(s: Scenario, given, where):
    """robot.corrected_model: its plant-side effects fill plant.effects, and the torque signal's
    time law also estimator.torque_lag_s / torque_delay_s (one source: a field the scenario also
    sets is an error, as are robot.model / robot.params beside it)."""
    if not s.robot.corrected_model:
        return
    from safesysid.systems.model.corrections import CorrectionError, plant_effects, read_correction, torque_lag_s

    for key in ("model", "params"):
        if key in (given.get("robot") or {}):
            raise ScenarioError(f"{where}: robot.{key}: not with robot.corrected_model (it names the model)")
    path = resolve_path(s.robot.corrected_model, scenario_dir(s))
    if not path.is_file():
        raise ScenarioError(f"{where}: robot.corrected_model: file {s.robot.corrected_model!r} not found")
    try:
        corr = read_correction(path)
        fields = plant_effects(corr)
        lag = torque_lag_s(corr)  # its interval when the diagnosis gives one
    except CorrectionError as err:
        raise ScenarioError(f"{where}: robot.corrected_model: {err}") from err
    check_starting_scenario(corr)
    set_by_user = (given.get("plant") or {}).get("effects") or {}
    for key, value in fields.items():
        if key in set_by_user:
            raise ScenarioError(f"{where}: plant.effects.{key}: also set by robot.corrected_model ({path.name})")
        setattr(s.plant.effects, key, value)
    # The estimator reads the same torque signal: its lag, and its shift against the motion
    # (a late reading pairs step k with a later sample, a late torque with an earlier one).
    sensor = {
        "torque_lag_s": lag,
        "torque_delay_s": fields.get("torque_sensor_delay_s", 0.0) - fields.get("time_delay_s", 0.0),
    }
    for key, value in sensor.items():
        if value and key in (given.get("estimator") or {}):
            raise ScenarioError(f"{where}: estimator.{key}: also set by robot.corrected_model ({path.name})")
        if value:
            setattr(s.estimator, key, value)


def check_starting_scenario(corr: "CorrectedModel") -> None:
    """A corrected model that starts from a scenario YAML: that scenario, validated (ScenarioError
    naming its file and key); systems/config.py starting_robot then reads only its robot section."""
    start = corr.model_path()
    if start.suffix.lower() in (".yaml", ".yml") and start.is_file():
        load_scenario(start)


def _read_layer(previous: Scenario, layer, where) -> Scenario:
    """`previous` with the keys of one layer (YAML text or a mapping) read over it."""
    import yaml
    from pydrake.common.yaml import yaml_load_typed

    raw = layer
    if isinstance(layer, str):
        try:
            raw = yaml.safe_load(layer)
        except yaml.YAMLError as err:
            mark = getattr(err, "problem_mark", None)
            line = f" line {mark.line + 1}" if mark else ""
            raise ScenarioError(f"{where}:{line} invalid YAML ({getattr(err, 'problem', err)})") from err
    if not raw:
        return previous
    errors = []
    _check(raw, Scenario, "", errors)
    if errors:
        raise ScenarioError(f"{where}: {errors[0]}")
    return yaml_load_typed(schema=Scenario, data=yaml.safe_dump(raw), defaults=previous)
