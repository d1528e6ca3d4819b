"""The JSON Schema of the TOML configuration, generated from the settings dataclasses.

The settings dataclasses that `branchrange.config.loader.Config` gathers stay the one description of the configuration:
each key's type comes from its annotation, its default from the class, its range from the class's
`limits` (`branchrange.core.settings_check.Limit`), its unit from its name's suffix (`_m`, `_s`,
`_px` …) and its description from the class docstring (`branchrange.config.descriptions`). Why
generated and not written: the schema then cannot drift from what the loader accepts, and a key
added to a dataclass is in the editor's completion the day it is added.

The shipped copy (`SCHEMA_PATH`, referenced by the `#:schema` line of `deploy/*.toml` for Taplo /
Even Better TOML) is this module's output, `branchrange config schema > FILE`; a test keeps the
two equal. The schema says what one key accepts; the checks between keys (`min_range_m` below
`max_range_m`, weights for a network backend) are `branchrange config check`'s.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path
from typing import Any

from branchrange.config.descriptions import class_summary, key_description
from branchrange.config.loader import Config
from branchrange.core.settings_check import Limit

#: The schema shipped in the package (package data `branchrange/config/*.json`).
SCHEMA_PATH = Path(__file__).with_name("config.schema.json")
#: The JSON Schema dialect of the generated schema.
DIALECT = "https://json-schema.org/draft/2020-12/schema"

#: A key's unit from its name's suffix, longest suffix first.
UNIT_SUFFIXES: tuple[tuple[str, str], ...] = (
    ("_m2_per_s", "m²/s"),
    ("_m_s", "m/s"),
    ("_deg", "degrees"),
    ("_px", "px"),
    ("_hz", "Hz"),
    ("_mb", "MiB"),
    ("_s", "s"),
    ("_m", "m"),
)

#: The JSON Schema type of each scalar annotation.
_JSON_TYPES: dict[Any, str] = {bool: "boolean", int: "integer", float: "number", str: "string"}


def unit_of(key: str) -> str:
    """The unit a key's name says its value is in ('m', 's', 'px' …); '' when its name says none."""
    return next((unit for suffix, unit in UNIT_SUFFIXES if key.endswith(suffix)), "")


def _json_value(value: Any) -> Any:
    """A default as JSON has it: tuples as lists."""
    return [_json_value(v) for v in value] if isinstance(value, tuple) else value


def _value_schema(annotation: Any, limit: Limit | None) -> dict[str, Any]:
    """The type keywords of a field annotated `annotation`; a list's limit applies to each item."""
    bounds = limit.as_schema() if limit else {}
    if annotation in _JSON_TYPES:
        return {"type": _JSON_TYPES[annotation], **bounds}
    items = typing.get_args(annotation)
    if typing.get_origin(annotation) is tuple and items[1:] == (Ellipsis,):
        return {"type": "array", "items": _value_schema(items[0], limit)}
    if typing.get_origin(annotation) is tuple and len(set(items)) == 1:
        # a fixed-length vector: `items` + length, which every draft and Taplo read alike
        length = len(items)
        return {"type": "array", "items": _value_schema(items[0], limit), "minItems": length, "maxItems": length}
    raise TypeError(f"no JSON Schema type for the settings annotation {annotation!r}")


def _key_schema(cls: type, key: str, annotation: Any, default: Any) -> dict[str, Any]:
    """One key's schema: title, description (with its unit), type, range and default."""
    unit = unit_of(key)
    description = key_description(cls, key)
    if unit:
        description = f"[{unit}] {description}".rstrip()
    schema: dict[str, Any] = {"title": key}
    if description:
        schema["description"] = description
    if unit:
        schema["x-unit"] = unit
    schema.update(_value_schema(annotation, getattr(cls, "limits", {}).get(key)))
    schema["default"] = _json_value(default)
    return schema


def table_schema(cls: type, name: str) -> dict[str, Any]:
    """The schema of the TOML table `[name]` read into settings dataclass `cls`: every field a key, a
    field that is itself a dataclass a sub-table, and no other key (`additionalProperties: false`)."""
    hints = typing.get_type_hints(cls)
    defaults = cls()
    properties: dict[str, Any] = {}
    for field in dataclasses.fields(cls):
        annotation = hints[field.name]
        if isinstance(annotation, type) and dataclasses.is_dataclass(annotation):
            properties[field.name] = table_schema(annotation, f"{name}.{field.name}")
        else:
            properties[field.name] = _key_schema(cls, field.name, annotation, getattr(defaults, field.name))
    return {
        "title": f"[{name}]",
        "description": class_summary(cls),
        "type": "object",
        "additionalProperties": False,
        "properties": properties,
    }


def config_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a BranchRange TOML configuration file."""
    sections = typing.get_type_hints(Config)
    return {
        "$schema": DIALECT,
        "title": "BranchRange configuration",
        "description": "A BranchRange TOML configuration (`branchrange daemon|serve|replay --config FILE`). "
        "Every key has a default; `branchrange config check FILE` also runs the checks between keys.",
        "type": "object",
        "additionalProperties": False,
        "properties": {name: table_schema(sections[name], name) for name in sections},
    }


def schema_text(schema: dict[str, Any]) -> str:
    """`schema` as the shipped file holds it: indented JSON, UTF-8 characters as they are."""
    return json.dumps(schema, indent=2, ensure_ascii=False) + "\n"
