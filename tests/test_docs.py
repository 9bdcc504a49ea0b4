"""The front door and the manual: README's shape, the docs site (built with warnings as errors),
the generated reference pages, the JSON Schemas, the Python API example and the exit status."""

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import SCHEMAS, validate_outputs
from safesysid import reference_docs
from safesysid.cli import main

ROOT = Path(__file__).resolve().parents[1]
# Pages other documents own (each keeps its own history out); the rest are checked here.
OTHERS = {"guarantees.md", "task-phase.md", "identification.md", "hardware.md", "own-robot.md", "diagnosis.md"}
HISTORY = re.compile(r"\b(session|wave|round)[ -]\d+", re.IGNORECASE)


def _python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), re.DOTALL)


def test_readme_is_a_front_door():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    blocks = re.findall(r"```bash\n(.*?)\n```", text, re.DOTALL)
    assert blocks[0].endswith("safesysid run --out out/quickstart")  # the two commands come first
    assert blocks[1].endswith(ci), "README's test command must be exactly what .ci/run runs"


@pytest.mark.parametrize(
    "path",
    [
        ROOT / "README.md",
        ROOT / "CHANGELOG.md",
        *sorted(p for p in (ROOT / "docs").glob("*.md") if p.name not in OTHERS),
    ],
)
def test_no_development_history_in_the_docs(path):
    """Round numbers stay out (the changelog carries history by version, not by round)."""
    hits = [m.group(0) for m in HISTORY.finditer(path.read_text())]
    assert not hits, f"{path.name}: {hits}"


def test_the_site_generates_its_reference_pages(tmp_path):
    """The docs site's scenario.md and cli.md are generated at build time by the hook."""
    page = type("Page", (), {"file": type("File", (), {"src_uri": "cli.md"})()})()
    assert reference_docs.on_page_read_source(page, None) == reference_docs.cli_reference()
    page.file.src_uri = "index.md"
    assert reference_docs.on_page_read_source(page, None) is None


def test_scenario_reference_lists_every_field():
    page = reference_docs.scenario_reference()
    rows = reference_docs.schema_rows()
    assert len(rows) > 100
    missing = [path for path, *_ in rows if f"| `{path}` |" not in page]
    assert not missing
    by_path = {row[0]: row for row in rows}
    assert by_path["planner.duration_s"][2] == "s" and by_path["noise.torque_floor_Nm"][2] == "N·m"
    assert by_path["payload.bounding_volume.shape"][4] == "none|ellipsoid|box"


def test_version(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0 and re.match(r"safesysid \d+\.\d+", capsys.readouterr().out)


def test_schemas_are_valid_json_schemas():
    jsonschema = pytest.importorskip("jsonschema")
    for path in SCHEMAS.glob("*.schema.json"):
        jsonschema.Draft202012Validator.check_schema(json.loads(path.read_text()))


def test_docs_site_builds_with_warnings_as_errors(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("material")
    mkdocs = [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml")]
    done = subprocess.run([*mkdocs, "-d", str(tmp_path / "site")], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "site" / "scenario" / "index.html").exists()


@pytest.fixture(scope="module")
def api_example(tmp_path_factory):
    """README's Python example, run as written in a scratch folder (its out/ goes there)."""
    (code,) = _python_blocks(ROOT / "README.md")
    folder = tmp_path_factory.mktemp("api")
    (folder / "scenarios").symlink_to(ROOT / "scenarios")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=folder)
    assert done.returncode == 0, done.stderr[-3000:]
    return folder, done.stdout


def test_the_python_api_example_runs_and_reads_the_estimate(api_example):
    folder, printed = api_example
    success, lower, upper, truth = printed.split()
    assert success == "True" and float(lower) <= float(truth) <= float(upper)
    assert validate_outputs(folder / "out") == 1  # its summary.json matches the published schema


def test_the_docs_python_examples_are_readmes(api_example):
    """The getting-started and API pages run the same call (README's is the one executed)."""
    readme = _python_blocks(ROOT / "README.md")[0]
    call = next(line for line in readme.splitlines() if line.startswith("scenario = "))
    for page in ("getting-started.md", "api.md"):
        assert call in _python_blocks(ROOT / "docs" / page)[0]


@pytest.mark.parametrize(
    "change, status", [({}, 0), ({"success": False, "failure": "collision"}, 1), ({"contains_truth": False}, 1)]
)
def test_run_exits_1_when_the_run_failed(api_example, monkeypatch, tmp_path, capsys, change, status):
    """`safesysid run`: 0 only on success, 1 when the run failed (a real run's summary, altered);
    the printout explains the identified mass (last link + gripper + dumbbell)."""
    import safesysid.online

    folder, _ = api_example
    summary = {**json.loads((folder / "out" / "api" / "summary.json").read_text()), **change}
    monkeypatch.setattr(safesysid.online, "run_online", lambda *args, **kwargs: summary)
    assert main(["run", "--out", str(tmp_path / "run"), "--no-serve"]) == status
    assert "identified body: last link + gripper 1.280 kg + 4lb dumbbell 1.814 kg = 3.094 kg" in capsys.readouterr().out


def test_compare_and_sweep_say_their_exit_status_in_help(capsys):
    for verb in ("compare", "sweep"):
        with pytest.raises(SystemExit):
            main([verb, "--help"])
        assert "exit status 0 when" in " ".join(capsys.readouterr().out.split()).lower()


def test_getting_started_blocks_name_existing_files():
    """Cheap check in CI: every scenario a getting-started command names exists (the full run of
    every block on a fresh clone is tests/test_getting_started.py)."""
    text = (ROOT / "docs" / "getting-started.md").read_text()
    for name in re.findall(r"scenarios/[\w.]+\.yaml", text):
        assert (ROOT / name).exists(), name
    assert shutil.which("git")
