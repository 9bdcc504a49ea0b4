"""Every robot constant the code uses, and the file it comes from; none is in systems/ or app/.

| constant | file |
|---|---|
| joint position, velocity and torque limits | the parameter YAML (models/*_params.yaml) = the URDF's <limit> |
| friction, armature, torque offsets | the parameter YAML |
| link masses, centres of mass, inertias, kinematics | the URDF (models/*.urdf, written by models/make_*_urdf.py) |
| end-effector body, grasp point | the parameter YAML (`end_effector_link`, `grasp_point_m`) |
| planner spheres | the sphere YAML the parameter YAML names (models/cover_spheres.py for Panda and UR5e) |
| q0, ARMOUR's Kr, the baselines' gains, k ranges, Fourier acceleration limits | the scenario (*) |
| the end-effector prior | the scenario: `initial_interval`, or derived from its payload range (*) |

(*) unset: the parameter YAML's `defaults:` (the Gen3's tuned values and Table II), else the rules
of systems/model/robot_defaults.py (no rule for a prior: an error naming the field).

test_every_robot_value_of_the_shipped_scenarios_names_its_file prints that table per scenario.
"""

import dataclasses as dc
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from safesysid.systems.model import robot_defaults as rd
from safesysid.systems.model.robot_model import MODELS_DIR, load_robot

ROOT = Path(__file__).resolve().parents[1]
PARAMS = ["kinova_gen3_params.yaml", "panda_params.yaml", "ur5e_params.yaml"]
LIMIT_FIELDS = ("position_lower_rad", "position_upper_rad", "velocity_limit_rad_s", "torque_limit_Nm")
SCENARIOS = {"quickstart.yaml": PARAMS[0], "panda_quickstart.yaml": PARAMS[1], "ur5e_quickstart.yaml": PARAMS[2]}


@pytest.mark.parametrize("params", PARAMS)
def test_the_limits_and_friction_the_code_uses_are_the_robot_files(params):
    """What load_robot hands every system is the parameter file's, and the URDF says the same."""
    doc = yaml.safe_load((MODELS_DIR / params).read_text())
    robot = load_robot(params_path=MODELS_DIR / params)
    jp = robot.joint_params
    used = {
        "position_lower_rad": jp.position_lower,
        "position_upper_rad": jp.position_upper,
        "velocity_limit_rad_s": jp.velocity_limit,
        "torque_limit_Nm": jp.torque_limit,
        "coulomb_Nm": jp.coulomb,
        "armature_kgm2": jp.armature,
    }
    for field, values in used.items():
        np.testing.assert_array_equal(values, np.asarray(doc["joints"].get(field, [0.0] * robot.n), float), field)
    urdf = (MODELS_DIR / doc["urdf"]).read_text()
    for k, name in enumerate(jp.names):
        limit = re.search(rf'<joint name="{name}"[^\n]*?<limit ([^/]*)/>', urdf).group(1)
        efforts = dict(re.findall(r'(\w+)="([^"]+)"', limit))
        assert float(efforts["effort"]) == pytest.approx(jp.torque_limit[k])
        assert float(efforts["velocity"]) == pytest.approx(jp.velocity_limit[k])
        if "lower" in efforts:
            assert float(efforts["lower"]) == pytest.approx(jp.position_lower[k])


def _literals(path):
    return set(re.findall(r"(?<![\w.])-?\d+\.\d+(?![\w.])", path.read_text()))


def _pi_fractions(path):
    """Values of `pi / N` and `pi * N` written in a file (a k range was once `np.pi / 48`)."""
    text = path.read_text()
    fractions = {np.pi / float(d) for d in re.findall(r"pi\s*/\s*(\d+(?:\.\d+)?)", text)}
    return {f"{x:g}" for x in fractions | {np.pi * float(m) for m in re.findall(r"pi\s*\*\s*(\d+\.\d+)", text)}}


def _robot_figures():
    """The figures of the shipped arms' files: limits, and the defaults with two or more significant
    digits (a 0, 0.5 or 100 says nothing about an arm), less the plot sizes 1.2 and 3.2 of app/."""
    figures = set()
    for params in PARAMS:
        doc = yaml.safe_load((MODELS_DIR / params).read_text())
        for field in LIMIT_FIELDS:
            figures |= {f"{v:g}" for v in doc["joints"][field] if np.isfinite(v) and abs(v) not in (0.0, 1.0)}
        for values in rd._flatten(doc.get("defaults") or {}).values():
            figures |= {f"{v:g}" for v in values if len(f"{abs(v):g}".replace(".", "").strip("0")) >= 2}
    return figures - {"3.14159", "6.28319", "-3.14159", "-6.28319", "1.2", "3.2"}  # pi, 2 pi: not robot figures


def test_no_robot_figure_is_written_in_systems_or_app():
    """The limit figures and tuned defaults of the three shipped arms appear in no module of
    systems/ or app/ (2 and 0.5 aside: too common to name an arm)."""
    figures = _robot_figures()
    assert {"5.2", "0.26", "180", "0.15708", "0.0654498", "12", "87"} <= figures  # the Gen3's tuned, Panda's limits
    hits = {}
    for folder in ("systems", "app"):
        for path in (ROOT / folder).rglob("*.py"):
            found = {x for x in _literals(path) if f"{float(x):g}" in figures and float(x) not in (2.0, 0.5)}
            found |= _pi_fractions(path) & figures
            if found:
                hits[str(path.relative_to(ROOT))] = sorted(found)
    assert hits == {}


def _list_defaults(cls, prefix=""):
    """(path, default) of every list field of the schema, sections walked."""
    out = []
    for field in dc.fields(cls):
        if field.default_factory is dc.MISSING:
            continue
        value = field.default_factory()
        if dc.is_dataclass(value):
            out += _list_defaults(type(value), f"{prefix}{field.name}.")
        elif isinstance(value, list):
            out.append((f"{prefix}{field.name}", value))
    return out


def test_the_schema_holds_no_per_joint_value_and_no_prior():
    """Every robot field of the schema is empty (unset: the robot's), and no other list default has
    a shipped arm's joint count: a per-joint value written into systems/config.py fails here."""
    from safesysid.systems.config import Scenario

    defaults = dict(_list_defaults(Scenario))
    assert set(rd.FIELDS) <= set(defaults)
    assert {f: defaults[f] for f in rd.FIELDS} == {f: [] for f in rd.FIELDS}
    joint_counts = {len(yaml.safe_load((MODELS_DIR / p).read_text())["joints"]["names"]) for p in PARAMS}
    assert {path: v for path, v in defaults.items() if len(v) in joint_counts} == {}


def _given(scenario_doc, field):
    node = scenario_doc
    for part in field.split("."):
        node = (node or {}).get(part)
    return node


@pytest.mark.parametrize("name", SCENARIOS)
def test_every_robot_value_of_the_shipped_scenarios_names_its_file(name):
    """Each robot field of a shipped scenario is the scenario's own, the parameter file's declared
    default, or the rule's, and the run gets exactly that value."""
    from safesysid.scenario import SCENARIOS_DIR, load_scenario

    doc = yaml.safe_load((SCENARIOS_DIR / name).read_text())
    params = MODELS_DIR / SCENARIOS[name]
    robot = load_robot(params_path=params)
    declared = rd.declared_defaults(yaml.safe_load(params.read_text()), n=robot.n, where=str(params))
    derived = rd.derived_defaults(robot)
    loaded = load_scenario(SCENARIOS_DIR / name)
    table = {}
    for field in rd.FIELDS:
        value = rd.field_value(loaded, field)
        if _given(doc, field) is not None:
            table[field] = (f"scenarios/{name}", _given(doc, field))
        elif field in declared:
            table[field] = (f"models/{SCENARIOS[name]} defaults", declared[field])
        elif field in rd.PRIOR:  # derived from the scenario's payload range
            table[field] = (f"scenarios/{name} initial_interval.payload_mass_kg", value)
            assert _given(doc, "initial_interval.payload_mass_kg")
        else:
            table[field] = ("systems/model/robot_defaults.py rule", derived[field])
        assert value == table[field][1], field
    print("\n".join(f"{name}: {field}: {src}" for field, (src, _) in table.items()))
    if name == "quickstart.yaml":  # the Gen3's tuned values and Table II from its file (q0 the scenario's too)
        assert {src for field, (src, _) in table.items() if field != "q0_rad"} == {f"models/{SCENARIOS[name]} defaults"}


@pytest.mark.parametrize("params", PARAMS[1:])
def test_the_derived_defaults_follow_their_documented_rules(params):
    """On the Panda and the UR5e: q0 the middle of the joint box, Kr = w / 2, the baselines' gains
    from the joint's largest inertia M_j (Kp = M_j w^2, Ki = Kp / 1 s, Kd = 2 zeta w M_j,
    adaptive Kd = w M_j), k ranges 50 ms and acceleration limits 1 / 0.25 s of the velocity limits."""
    robot = load_robot(params_path=MODELS_DIR / params)
    jp, n, w = robot.joint_params, robot.n, rd.BANDWIDTH_RAD_S
    got = {k: np.array(v) for k, v in rd.derived_defaults(robot).items()}
    assert set(got) == set(rd.PER_JOINT) and all(v.shape == (n,) for v in got.values())
    q0 = got["q0_rad"]
    assert np.all((jp.position_lower <= q0) & (q0 <= jp.position_upper))
    np.testing.assert_allclose(
        q0, np.where(np.isfinite(jp.position_lower), (jp.position_lower + jp.position_upper) / 2, 0)
    )
    inertia = got["controller.adaptive_kd_Nms_rad"] / w
    # M_j: the largest diagonal entry seen, never below the armature, and at least the entry at q0
    assert np.all(inertia >= jp.armature)
    assert np.all(inertia >= np.diag(robot.mass_matrix(q0)[0]) * (1 - 0.2))
    np.testing.assert_allclose(got["controller.Kr"], w / 2)
    np.testing.assert_allclose(got["controller.pid_kp_Nm_rad"], inertia * w**2)
    np.testing.assert_allclose(got["controller.pid_ki_Nm_rad_s"], inertia * w**2 * rd.INTEGRAL_CORNER_RAD_S)
    np.testing.assert_allclose(got["controller.pid_kd_Nms_rad"], 2 * rd.DAMPING_RATIO * w * inertia)
    np.testing.assert_allclose(got["planner.k_center_rad"], 0.0)
    np.testing.assert_allclose(got["planner.k_range_rad"], jp.velocity_limit * rd.RANGE_TIME_S)
    np.testing.assert_allclose(got["fourier.acceleration_limit_rad_s2"], jp.velocity_limit / rd.ACCELERATION_TIME_S)


def test_a_scenario_built_in_code_resolves_as_a_loaded_one():
    """The library path: Scenario() made in code gets the robot's values when the robot is read
    (robot_from_scenario, as every run does), the same as load_scenario's; a robot without a
    declared prior and no payload range is an error naming the field."""
    from safesysid.scenario import load_scenario
    from safesysid.systems.config import Robot, Scenario, ScenarioError
    from safesysid.systems.model.loading import robot_from_scenario

    prior = load_scenario().initial_interval  # the Gen3's Table II, given to both
    for params in PARAMS[:2]:
        s = Scenario(robot=Robot(params=f"builtin:{params}"), initial_interval=prior)
        assert s.q0_rad == [] and s.controller.Kr == []
        robot_from_scenario(s)
        layer = {"robot": {"params": f"builtin:{params}"}, "initial_interval": dc.asdict(prior)}
        loaded = load_scenario(text=yaml.safe_dump(layer))
        for field in rd.PER_JOINT:
            assert rd.field_value(s, field) == rd.field_value(loaded, field), field
    with pytest.raises(ScenarioError, match=r"initial_interval: .*ur5e_params.yaml declares no prior"):
        robot_from_scenario(Scenario(robot=Robot(params="builtin:ur5e_params.yaml")))
    with pytest.raises(ScenarioError, match=r"defaults: initial_interval: .*ur5e_params.yaml declares no prior"):
        load_scenario(text="robot: {params: 'builtin:ur5e_params.yaml'}")


def test_a_model_file_alone_takes_the_defaults_of_the_parameter_file_that_names_it(tmp_path):
    """A diagnosis' corrected model starts from a URDF alone: the Gen3's URDF still has the Gen3's
    defaults (kinova_gen3_params.yaml names it); a copy elsewhere has none to take, so its prior is
    left out and the rest derived."""
    import shutil

    declared = yaml.safe_load((MODELS_DIR / PARAMS[0]).read_text())["defaults"]
    values = rd.robot_defaults(load_robot(model_path=MODELS_DIR / "kinova_gen3.urdf"))
    assert (
        values["q0_rad"] == declared["q0_rad"]
        and values["initial_interval.lower"] == declared["initial_interval"]["lower"]
    )
    shutil.copy(MODELS_DIR / "kinova_gen3.urdf", tmp_path / "arm.urdf")
    copy = rd.robot_defaults(load_robot(model_path=tmp_path / "arm.urdf"))
    assert "initial_interval.lower" not in copy and copy["controller.Kr"] == [rd.BANDWIDTH_RAD_S / 2] * 7


def test_a_scenario_that_sets_the_lists_keeps_them():
    from safesysid.scenario import SCENARIOS_DIR, load_scenario

    layer = "controller: {Kr: [6.0, 6.0, 6.0, 6.0, 6.0, 6.0]}\nplanner: {k_range_rad: [0.1, 0.1, 0.1, 0.1, 0.1, 0.1]}"
    s = load_scenario(SCENARIOS_DIR / "ur5e_quickstart.yaml", overrides=layer)
    assert s.controller.Kr == [6.0] * 6 and s.planner.k_range_rad == [0.1] * 6


@pytest.mark.parametrize(
    "defaults, message",
    [
        ("defaults: {controler: {Kr: [1, 1, 1, 1, 1, 1, 1]}}", r"defaults\.controler\.Kr: unknown key"),
        ("defaults: {controller: {Kr: [1, 1]}}", r"defaults\.controller\.Kr: needs 7 numbers"),
        ("defaults: {initial_interval: {nominal: [1, 2, 3]}}", r"defaults\.initial_interval\.nominal: needs 10"),
    ],
)
def test_a_wrong_defaults_section_names_the_file_and_the_key(tmp_path, defaults, message):
    from safesysid.scenario import ScenarioError, load_scenario

    doc = (MODELS_DIR / PARAMS[0]).read_text().split("\ndefaults:")[0].replace("urdf: ", f"urdf: {MODELS_DIR}/")
    (tmp_path / "arm.yaml").write_text(doc + "\n" + defaults + "\n")
    with pytest.raises(ScenarioError, match="arm.yaml: " + message):
        load_scenario(
            text=f"robot: {{params: '{tmp_path / 'arm.yaml'}'}}\ninitial_interval: {{payload_mass_kg: [1, 2]}}"
        )
