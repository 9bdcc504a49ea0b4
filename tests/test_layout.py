"""Layering: systems/ (Drake systems and their math) imports nothing from app/ (loading, CLI,
reports); the scenario schema it needs is systems/config.py."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
APP_MODULES = {p.stem for p in (ROOT / "app").glob("*.py")} - {"__init__"}
# Pending: the gap-diagnosis split (gap_simulate builds its log from app's JointLog and
# load_scenario); remove it from here when that module moves.
PENDING = {"gap_simulate.py"}


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
    offenders = {str(p.relative_to(ROOT)): app_imports(p) for p in sorted((ROOT / "systems").rglob("*.py"))
                 if p.name not in PENDING}
    assert {k: v for k, v in offenders.items() if v} == {}


def test_the_check_sees_a_function_local_import(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from safesysid.scenario import load_scenario\n    from safesysid import online\n")
    assert app_imports(probe) == [(2, "safesysid.scenario"), (3, "safesysid.online")]
