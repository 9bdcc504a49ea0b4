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


def test_every_system_of_the_online_diagram_is_a_module_level_class_stepping_with_the_plant():
    """For a method of every controller kind, with every per-step effect of the real arm on: GetSystemType()
    names a module-level class (a class made inside a factory is a new class per call:
    '...<locals>.ArmourController'), and no system has a periodic discrete update: Drake's
    discrete MultibodyPlant steps in the unrestricted phase, and a discrete update runs after it,
    reading x_k+1 at t_k (a delay stage would store a torque never applied; test_plant_friction.py
    test_late_*)."""
    from helpers import leaves
    from safesysid.online import build_online
    from safesysid.scenario import SCENARIOS_DIR, load_scenario

    effects = (
        "plant: {time_step_s: 0.00025, effects: {joint_elasticity: dynamic, joint_stiffness_Nm_rad: [1.0e+4, "
        "1.0e+4, 1.0e+4, 1.0e+4, 4.0e+3, 4.0e+3, 4.0e+3], time_delay_s: 0.001, torque_sensor_delay_s: 0.001, "
        "torque_sensor_lag_s: 0.01, velocity_noise_rad_s: 0.001}}"
    )
    scene = load_scenario(SCENARIOS_DIR / "quickstart.yaml", overrides=effects)
    controllers = {"ours": "ArmourController", "grav-pid": "GravityPidController", "adap-2": "AdaptiveController"}
    for method, controller in controllers.items():
        systems = list(leaves(build_online(scene, method).diagram))
        types = {s.GetSystemType() for s in systems}
        assert not [t for t in types if "<locals>" in t]
        stages = {"TorqueSensor", "StepDelay", "ElasticTransmission", controller}
        assert stages <= {t.rsplit(".", 1)[-1] for t in types}
        assert [s.get_name() for s in systems if s.GetUniquePeriodicDiscreteUpdateAttribute() is not None] == []


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


# The roles of safesysid.systems, lowest first: a role imports only the roles listed for it (and
# itself). config.py and methods.py are the schema (the scenario's fields and the paper's methods
# as data); app/ may import anything.
ROLE_IMPORTS = {
    "schema": set(),
    "math": set(),
    "model": {"schema", "math"},
    "controller": {"schema", "math", "model"},
    # estimation: the planner's interval dynamics (one interval RNEA for both: the derived acceleration bound)
    "estimation": {"schema", "math", "model", "planner"},
    "planner": {"schema", "math", "model", "controller"},
    "hardware": {"schema", "math", "model", "controller", "estimation", "planner", "plant"},
    "plant": {"schema", "math", "model", "controller", "estimation", "planner"},
    "excitation": {"schema", "math", "model", "controller", "planner"},
    "task": {"schema", "math", "model", "controller", "estimation", "planner", "plant", "excitation"},
    "diagnosis": {"schema", "math", "model", "controller", "estimation", "planner", "plant"},
}
SCHEMA = {"config", "methods"}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    top = {"app": ["safesysid"], "systems": ["safesysid", "systems"]}[parts[0]]
    rest = parts[1:-1] if parts[-1] == "__init__" else parts[1:]
    return ".".join(top + rest)


def role_of(module: str) -> str | None:
    """The role of a safesysid.systems module (None outside systems/)."""
    parts = module.split(".")
    if parts[:2] != ["safesysid", "systems"] or len(parts) < 3:
        return None
    return "schema" if parts[2] in SCHEMA else parts[2]


def imports_of(path: Path, *, runtime_only: bool = False) -> set[str]:
    """Every project module `path` imports (function-local ones included; TYPE_CHECKING blocks
    left out with runtime_only)."""
    tree = ast.parse(path.read_text())
    skip = set()
    if runtime_only:
        for node in ast.walk(tree):
            if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
                skip |= {id(n) for n in ast.walk(node)}
    here = module_name(path)
    package = here if path.name == "__init__.py" else here.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - (node.level - 1)] if node.level else []
            target = ".".join(base + ([node.module] if node.module else []))
            found |= {target} | {f"{target}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
    return {m for m in found if m.startswith("safesysid")}


def project_graph(*, runtime_only: bool) -> dict[str, set[str]]:
    files = sorted((ROOT / "systems").rglob("*.py")) + sorted((ROOT / "app").rglob("*.py"))
    modules = {module_name(p): p for p in files}
    return {
        m: {t for t in imports_of(p, runtime_only=runtime_only) if t in modules and t != m} for m, p in modules.items()
    }


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return found


# Cycles made only of annotations (TYPE_CHECKING imports; nothing runs them), each with its reason.
TYPE_ONLY_CYCLES = []


def test_no_import_cycles():
    assert cycles(project_graph(runtime_only=True)) == []
    assert sorted(cycles(project_graph(runtime_only=False))) == sorted(TYPE_ONLY_CYCLES)


def test_each_role_imports_only_the_roles_below_it():
    offenders = []
    for module, targets in project_graph(runtime_only=False).items():
        role = role_of(module)
        if role is None:
            continue
        for target in targets:
            other = role_of(target)
            if other is None and target.startswith("safesysid.systems"):
                continue  # the package itself
            if other != role and other not in ROLE_IMPORTS.get(role, set()):
                offenders.append(f"{module} ({role}) imports {target} ({other})")
    assert offenders == []


def test_the_layout_checks_see_a_cycle_and_a_role_violation():
    graph = {"a": {"b"}, "b": {"a"}, "c": {"a"}}
    assert cycles(graph) == [["a", "b"]]
    assert role_of("safesysid.systems.planner.safe_planner") == "planner"
    assert role_of("safesysid.systems.config") == "schema"
    assert "planner" not in ROLE_IMPORTS["model"]


# Size rules: a module of at most 500 lines, a function of at most 80 lines and cyclomatic
# complexity (ruff's C901, McCabe) at most 15. At most five exceptions, each with its reason.
MAX_MODULE_LINES, MAX_FUNCTION_LINES, MAX_COMPLEXITY = 500, 80, 15
SIZE_EXCEPTIONS: dict[str, str] = {}


def size_offenders(paths: list[Path], root: Path = ROOT) -> dict[str, str]:
    """{"file" or "file:function": what is over} for modules, functions (methods and nested ones
    included) and cyclomatic complexities over the limits."""
    import json
    import subprocess
    import sys

    found = {}
    for path in paths:
        name = str(path.relative_to(root))
        text = path.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            found[name] = f"{len(text.splitlines())} lines"
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    found[f"{name}:{node.name}"] = f"{length} lines"
    ruff = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--isolated", "--select", "C901", "--output-format", "json"]
        + ["--config", f"lint.mccabe.max-complexity={MAX_COMPLEXITY}", "--exit-zero", *map(str, paths)],
        capture_output=True,
        text=True,
        check=True,
    )
    for item in json.loads(ruff.stdout):
        function = item["message"].split("`")[1]
        key = f"{Path(item['filename']).resolve().relative_to(root)}:{function}"
        found[key] = (found[key] + ", " if key in found else "") + item["message"].split("is ")[-1]
    return found


def test_modules_and_functions_are_small():
    assert len(SIZE_EXCEPTIONS) <= 5
    files = [p for folder in ("app", "systems") for p in sorted((ROOT / folder).rglob("*.py"))]
    over = size_offenders(files)
    assert {k: v for k, v in over.items() if k not in SIZE_EXCEPTIONS} == {}


def test_the_size_check_sees_a_long_module_a_long_function_and_a_complex_one(tmp_path):
    probe = tmp_path / "probe.py"
    long_body = "".join(f"    x{i} = {i}\n" for i in range(80))
    complex_body = "".join(f"    if x == {i}:\n        return {i}\n" for i in range(15))
    short = "".join(f"y{i} = {i}\n" for i in range(420))
    probe.write_text(f"def long(x):\n{long_body}\n\ndef tangled(x):\n{complex_body}    return -1\n\n{short}")
    assert size_offenders([probe], root=tmp_path) == {
        "probe.py": "536 lines",
        "probe.py:long": "81 lines",
        "probe.py:tangled": "too complex (16 > 15)",
    }
