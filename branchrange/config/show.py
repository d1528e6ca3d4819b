"""`branchrange config show`: the effective configuration, every key, and where each value came from.

A daemon's behaviour depends on ~140 keys of which a deploy file sets ~40; the rest are defaults
that change between versions. This lists all of them as the code will use them, each marked
`default`, `file` or `--set`, as TOML (readable, and a valid file to start from) or as JSON.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from branchrange.config.loader import Config

#: Keys whose value is a secret: shown as set or not, never echoed.
SECRET_KEYS = frozenset({"api.token"})
#: How a secret that is set is shown.
HIDDEN = "(set, hidden)"


@dataclass(frozen=True)
class EffectiveSetting:
    """One key of the effective configuration: its dotted name, its value and its source
    ('default', 'file' or '--set')."""

    key: str
    value: Any
    source: str


def _leaves(settings: object, prefix: str) -> Iterator[tuple[str, Any]]:
    """(dotted key, value) of every field of a settings dataclass, sub-tables' fields included."""
    for field in dataclasses.fields(settings):  # type: ignore[arg-type]
        value = getattr(settings, field.name)
        if dataclasses.is_dataclass(value):
            yield from _leaves(value, f"{prefix}{field.name}.")
        else:
            yield f"{prefix}{field.name}", value


def effective_settings(cfg: Config, sources: dict[str, str]) -> list[EffectiveSetting]:
    """Every key of `cfg` in the order of the settings classes, with its source from `sources` (dotted key →
    'file' or '--set'; a key not in it is a default); secrets hidden."""
    settings = []
    for key, value in _leaves(cfg, ""):
        if key in SECRET_KEYS and value:
            value = HIDDEN
        elif isinstance(value, tuple):
            value = list(value)
        settings.append(EffectiveSetting(key, value, sources.get(key, "default")))
    return settings


def toml_value(value: Any) -> str:
    """`value` written as TOML: true/false, numbers (inf, nan), quoted strings, [lists]."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a JSON string is a TOML basic string
    return repr(value)


def as_toml(settings: list[EffectiveSetting]) -> str:
    """The settings as a TOML document, one `[table]` per section and sub-table, each value's source in a
    comment after it."""
    tables: dict[str, list[EffectiveSetting]] = {}
    for setting in settings:
        table, _, _ = setting.key.rpartition(".")
        tables.setdefault(table, []).append(setting)
    blocks = []
    for table, members in tables.items():
        rows = [(f"{s.key.rpartition('.')[2]} = {toml_value(s.value)}", s.source) for s in members]
        width = max(len(row) for row, _ in rows)
        blocks.append(f"[{table}]\n" + "".join(f"{row:<{width}}  # {source}\n" for row, source in rows))
    return "\n".join(blocks)


def as_json(settings: list[EffectiveSetting]) -> dict[str, dict[str, Any]]:
    """The settings as JSON: dotted key → {"value", "source"}."""
    return {s.key: {"value": s.value, "source": s.source} for s in settings}
