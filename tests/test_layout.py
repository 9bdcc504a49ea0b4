"""Layering: systems/ (Drake systems and their math) imports nothing from app/ (loading, CLI,
reports); the scenario schema it needs is systems/config.py."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
APP_MODULES = {p.stem for p in (ROOT / "app").glob("*.py")} - {"__init__"}
# Pending: the gap-diagnosis split (gap_simulate builds its log from app's JointLog and
# load_scenario); remove it from here when that module moves.
# Still importing app/ (JointLog and the scenario loader live there); the next step of the
# architecture issue moves JointLog to systems/ and passes model_corrections a loaded robot.
PENDING = {"gap_simulate.py", "arm_tracking.py", "model_corrections.py"}


def app_imports(path):
    """(line, module) of every import of an app/ module in `path`, function-local ones included."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            parts = node.module.split(".")
            if parts[0] == "safesysid" and len(parts) > 1 and parts[1] in APP_MODULES:
                found.append((node.lineno, node.module))
            elif node.module == "safesysid":
                found += [(node.lineno, f"safesysid.{a.name}") for a in node.names if a.name in APP_MODULES]
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == "safesysid" and len(parts) > 1 and parts[1] in APP_MODULES:
                    found.append((node.lineno, a.name))
    return found


def test_systems_import_nothing_from_app():
    offenders = {
        str(p.relative_to(ROOT)): app_imports(p)
        for p in sorted((ROOT / "systems").rglob("*.py"))
        if p.name not in PENDING
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_the_check_sees_a_function_local_import(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from safesysid.scenario import load_scenario\n    from safesysid import online\n")
    assert app_imports(probe) == [(2, "safesysid.scenario"), (3, "safesysid.online")]


def test_every_system_of_the_online_diagram_is_a_module_level_class():
    """GetSystemType() names a module-level class (a class made inside a factory is a new class
    per call: '...<locals>.ArmourController'), for every controller kind."""
    from pydrake.systems.framework import Diagram
    from safesysid.online import build_online
    from safesysid.scenario import SCENARIOS_DIR, load_scenario

    def leaves(system):
        if isinstance(system, Diagram):
            for sub in system.GetSystems():
                yield from leaves(sub)
        yield system

    for kind in ("armour", "pid", "adaptive", "adaptive_robust"):
        built = build_online(
            load_scenario(SCENARIOS_DIR / "quickstart.yaml", overrides=f"controller: {{kind: {kind}}}")
        )
        types = {s.GetSystemType() for s in leaves(built.diagram)}
        assert not [t for t in types if "<locals>" in t]
        assert any(t.endswith("real_arm.TorqueSensor") for t in types)
