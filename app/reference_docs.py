"""Reference pages generated from the code: the scenario schema (systems/config.py) and the CLI
(argparse), so the documentation cannot drift from what the program accepts.

The docs site generates both at build time (this module is a MkDocs hook: mkdocs.yml `hooks`);
`python -m safesysid.reference_docs docs` rewrites the committed copies in docs/.
"""

from __future__ import annotations

import argparse
import dataclasses as dc
import inspect
import re
import sys
import typing
from pathlib import Path

from safesysid.systems import config

# Field-name suffixes and the unit they declare (the schema's convention: units in the names).
UNIT_SUFFIXES = (
    ("_Nms_rad", "N·m·s/rad"),
    ("_Nm_rad_s", "N·m/(rad·s)"),
    ("_Nm_rad", "N·m/rad"),
    ("_rad_s2", "rad/s²"),
    ("_rad_s", "rad/s"),
    ("_per_s", "1/s"),
    ("_kgm2", "kg·m²"),
    ("_kgm", "kg·m"),
    ("_Nm", "N·m"),
    ("_kg", "kg"),
    ("_rad", "rad"),
    ("_m", "m"),
    ("_s", "s"),
    ("_hz", "Hz"),
)


def unit_of(name: str) -> str:
    """The unit a field name declares by its suffix, or '' (dimensionless or stated in the text)."""
    return next((unit for suffix, unit in UNIT_SUFFIXES if name.endswith(suffix)), "")


def _field_comments(cls: type) -> dict[str, str]:
    """Each field's comment in the class source: the comment lines above it plus its inline comment."""
    comments, pending = {}, []
    for line in inspect.getsource(cls).splitlines()[1:]:
        stripped = line.strip()
        if stripped.startswith("#"):
            pending.append(stripped.lstrip("# "))
            continue
        match = re.match(r"\s+(\w+)\s*:[^#]*(?:#\s*(.*))?$", line)
        if match and not stripped.startswith(("def ", '"""', "@")):
            comments[match.group(1)] = " ".join([*pending, match.group(2) or ""]).strip()
        pending = []
    return comments


def _type_name(tp) -> str:
    origin = typing.get_origin(tp)
    if origin in (list, typing.List):  # noqa: UP006 (the schema's own alias)
        return f"list of {_type_name(typing.get_args(tp)[0])}"
    if origin is typing.Union:
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        return f"{_type_name(inner[0])} or null"
    return getattr(tp, "__name__", str(tp))


def _default(field: dc.Field) -> str:
    if field.default is not dc.MISSING:
        value = field.default
    elif field.default_factory is not dc.MISSING:
        value = field.default_factory()
    else:
        return "(required)"
    return "(section)" if dc.is_dataclass(value) else f"`{value!r}`"


def _dataclass_of(tp):
    for candidate in (tp, *typing.get_args(tp)):
        if dc.is_dataclass(candidate):
            return candidate
    return None


def schema_rows(cls: type = config.Scenario, prefix: str = "") -> list[tuple[str, str, str, str, str, str]]:
    """(path, type, unit, default, choices, description) for every field, sections before their fields."""
    hints = typing.get_type_hints(cls)
    comments = _field_comments(cls)
    rows = []
    for field in dc.fields(cls):
        path, comment = f"{prefix}{field.name}", comments.get(field.name, "")
        nested = _dataclass_of(hints[field.name])
        if nested is not None and not comment:
            comment = (inspect.getdoc(nested) or "").split("\n\n")[0]
        choices = field.metadata.get("choices") or ()
        rows.append(
            (
                path,
                _type_name(hints[field.name]),
                unit_of(field.name),
                _default(field),
                "|".join(choices),
                comment,
            )
        )
        if nested is not None:
            sep = "[]." if typing.get_origin(hints[field.name]) in (list, typing.List) else "."  # noqa: UP006
            rows.extend(schema_rows(nested, f"{path}{sep}"))
    return rows


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def scenario_reference() -> str:
    """docs/scenario.md: every field of the scenario schema with its type, unit, default and choices."""
    head = [
        "# Scenario reference",
        "",
        "Generated from `systems/config.py` at each docs build (the committed copy: `python -m",
        "safesysid.reference_docs docs`). A scenario file names only what it changes; the",
        "defaults below fill the rest. Units are in the field names; `a|b` lists the accepted choices.",
        f"Methods (`method`): {', '.join(f'`{m}`' for m in config.METHODS)}.",
        "",
        "| field | type | unit | default | choices | description |",
        "|---|---|---|---|---|---|",
    ]
    body = [f"| `{p}` | {t} | {u} | {_cell(d)} | {_cell(c)} | {_cell(text)} |" for p, t, u, d, c, text in schema_rows()]
    return "\n".join(head + body) + "\n"


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def cli_reference() -> str:
    """docs/cli.md: `safesysid --help` and each verb's --help, verbatim."""
    from safesysid.cli import build_parser

    parser = build_parser()
    parts = [
        "# CLI reference",
        "",
        "Generated from the argparse parser at each docs build (the committed copy: `python -m",
        "safesysid.reference_docs docs`).",
        "Exit status: 0 success, 1 the run failed, 2 bad input; `compare` and `sweep` exit 0 when they",
        "completed (their runs' failures are data in their tables).",
        "",
        "```text",
        _help(parser),
        "```",
    ]
    for verb, sub in _subcommands(parser).items():
        parts += ["", f"## safesysid {verb}", "", "```text", _help(sub), "```"]
    return "\n".join(parts) + "\n"


def _help(parser: argparse.ArgumentParser) -> str:
    import os

    saved = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # the same wrapping on every terminal
    try:
        return parser.format_help().rstrip()
    finally:
        if saved is None:
            os.environ.pop("COLUMNS")
        else:
            os.environ["COLUMNS"] = saved


PAGES = {"scenario.md": scenario_reference, "cli.md": cli_reference}


def on_page_read_source(page: object, config: object) -> str | None:
    """MkDocs hook (mkdocs.yml `hooks`): the site's reference pages are generated at build time,
    so they always match the code; the committed copies are for reading on a forge."""
    make = PAGES.get(page.file.src_uri)
    return make() if make else None


def main(argv: list[str] | None = None) -> int:
    docs = Path((argv or sys.argv[1:] or ["docs"])[0])
    for name, make in PAGES.items():
        (docs / name).write_text(make())
    return 0


if __name__ == "__main__":
    sys.exit(main())
