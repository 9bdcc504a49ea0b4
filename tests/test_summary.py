"""summary.json's typed schema (app/summary.py Summary) and its published JSON Schema
(docs/schemas/summary.schema.json) name the same fields and require the same keys, level by level."""

import dataclasses
import json
import typing
from pathlib import Path

from safesysid import summary as summary_module
from safesysid.summary import OMITTED, EstimateSummary, Summary, as_json

SCHEMA = Path(__file__).resolve().parents[1] / "docs" / "schemas" / "summary.schema.json"


def nested_dataclass(cls, name):
    """The dataclass a field of `cls` holds (None: a plain value)."""
    hint = typing.get_type_hints(cls, vars(summary_module))[name]
    return hint if dataclasses.is_dataclass(hint) else None


def disagreements(cls, schema, where="summary"):
    """'where: problem' for each field name or required key the dataclass and the schema differ on."""
    fields = [f.name for f in dataclasses.fields(cls)]
    always = [f.name for f in dataclasses.fields(cls) if not f.metadata.get("optional")]
    found = []
    if fields != list(schema.get("properties", {})):
        found.append(f"{where}: fields {fields} != schema properties {list(schema.get('properties', {}))}")
    if always != schema.get("required", []):
        found.append(f"{where}: always written {always} != schema required {schema.get('required', [])}")
    for name in fields:
        inner = nested_dataclass(cls, name)
        if inner is not None:
            found += disagreements(inner, schema["properties"].get(name, {}), f"{where}.{name}")
    return found


def test_the_summary_dataclass_is_the_published_schema():
    assert disagreements(Summary, json.loads(SCHEMA.read_text())) == []


def test_the_check_sees_a_field_the_schema_lacks_and_a_key_it_does_not_require():
    schema = json.loads(SCHEMA.read_text())
    del schema["properties"]["planner"]["properties"]["refined"]
    schema["properties"]["estimate"]["required"].remove("consistent")
    problems = disagreements(Summary, schema)
    assert len(problems) == 2
    assert problems[0].startswith("summary.estimate: always written") and "consistent" in problems[0]
    assert problems[1].startswith("summary.planner: fields") and "refined" in problems[1]


def test_omitted_fields_leave_their_key_out_and_none_is_written_as_null():
    est = EstimateSummary(nominal=[1.0], lower=[0.0], upper=[2.0], consistent=True, data_lower=None, source="none")
    assert as_json(est) == {
        "nominal": [1.0],
        "lower": [0.0],
        "upper": [2.0],
        "consistent": True,
        "data_lower": None,
        "source": "none",
    }
    assert est.data_upper is OMITTED
