"""Layout rules: systems/ (Drake systems and their math) imports nothing from app/ (loading, CLI,
reports; the scenario schema it needs is systems/config.py); every LeafSystem of the online
diagram is a module-level class; public functions and dataclass fields carry type hints."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
APP_MODULES = {p.stem for p in (ROOT / "app").glob("*.py")} - {"__init__"}


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
    offenders = {str(p.relative_to(ROOT)): app_imports(p) for p in sorted((ROOT / "systems").rglob("*.py"))}
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


def _is_dataclass(node):
    names = [d.func if isinstance(d, ast.Call) else d for d in node.decorator_list]
    return any((n.attr if isinstance(n, ast.Attribute) else getattr(n, "id", "")) == "dataclass" for n in names)


def untyped(path):
    """'line name: problem' for each public top-level function and public method of a top-level
    class without annotations on every parameter (self/cls aside) and on its return, and each
    dataclass field typed `object`."""
    found = []

    def check_function(fn, method):
        args = fn.args.posonlyargs + fn.args.args + fn.args.kwonlyargs
        if method and args and args[0].arg in ("self", "cls"):
            args = args[1:]
        args += [a for a in (fn.args.vararg, fn.args.kwarg) if a is not None]
        missing = [a.arg for a in args if a.annotation is None]
        if missing:
            found.append(f"{fn.lineno} {fn.name}: parameters {', '.join(missing)} not annotated")
        if fn.returns is None:
            found.append(f"{fn.lineno} {fn.name}: no return annotation")

    functions = (ast.FunctionDef, ast.AsyncFunctionDef)
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, functions) and not node.name.startswith("_"):
            check_function(node, method=False)
        elif isinstance(node, ast.ClassDef):
            for item in node.body:
                if isinstance(item, functions) and not item.name.startswith("_") and not node.name.startswith("_"):
                    check_function(item, method=True)
                elif isinstance(item, ast.AnnAssign) and _is_dataclass(node):
                    if any(isinstance(n, ast.Name) and n.id == "object" for n in ast.walk(item.annotation)):
                        found.append(f"{item.lineno} {node.name}.{ast.unparse(item.target)}: typed object")
    return found


def test_the_annotation_check_sees_what_is_missing(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text(
        "from dataclasses import dataclass\n"
        "def f(a: int, b) -> int: ...\n"
        "def g(a: int): ...\n"
        "def _private(a): ...\n"
        "@dataclass\n"
        "class D:\n"
        "    x: object = None\n"
        "    y: int | None = None\n"
        "    def m(self, k): ...\n"
        "    def ok(self, k: int) -> None: ...\n"
    )
    assert untyped(probe) == [
        "2 f: parameters b not annotated",
        "3 g: no return annotation",
        "7 D.x: typed object",
        "9 m: parameters k not annotated",
        "9 m: no return annotation",
    ]


def test_public_functions_and_dataclass_fields_are_annotated():
    files = [p for folder in ("app", "systems") for p in sorted((ROOT / folder).rglob("*.py"))]
    offenders = {str(p.relative_to(ROOT)): untyped(p) for p in files}
    assert {k: v for k, v in offenders.items() if v} == {}
