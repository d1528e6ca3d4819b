"""`branchrange config check`: every problem of a configuration file at once, each with its key and line.

The loader (`branchrange.config.loader.load_config`) stops at the first error, which is right for a
daemon starting on the drone; a person editing the file wants all of them, where they are. So the
file (with the command line's `--set`s applied) is validated against the generated JSON Schema
(`branchrange.config.schema`: types, ranges, unknown keys with the nearest known name), then,
section by section, by the settings classes themselves for what the schema cannot say (the checks
between keys). tomllib gives no positions, so each key's line is found by reading the file for its
table header and `key =` line (`key_lines`); a key set with `--set` is reported as such.
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jsonschema

from branchrange.config.loader import (
    Config,
    Override,
    config_from_dict,
    unknown_option,
    unknown_section,
    with_overrides,
)
from branchrange.config.schema import config_schema
from branchrange.core.settings_check import ConfigError

#: A table header line: `[section]` or `[section.sub]`, perhaps with a comment after it.
_TABLE_HEADER = re.compile(r"^\s*\[\s*([\w.\- ]+?)\s*\]\s*(?:#.*)?$")
#: A key line: `key = value`, or a dotted key `table.key = value`.
_KEY_LINE = re.compile(r"^\s*([\w\-]+(?:\s*\.\s*[\w\-]+)*)\s*=")
#: Where tomllib says a syntax error is.
_TOML_ERROR_LINE = re.compile(r"at line (\d+)")
#: The dotted key a `ConfigError` message starts with (`cutpoints.min_points = 2: …`, `[mavlnk]: …`).
_MESSAGE_KEY = re.compile(r"^\[?([\w.]+)")
#: Where a value set on the command line comes from, in problems and in `config show`.
FROM_SET = "--set"


@dataclass(frozen=True)
class ConfigProblem:
    """One thing wrong with a configuration: the dotted key at fault ('' for the file itself), the
    message (which names the key) and where the value was written (`FILE:LINE`, `FILE` or `--set`)."""

    key: str
    message: str
    where: str

    def __str__(self) -> str:
        return f"{self.where}: {self.message}"


@dataclass(frozen=True)
class ConfigCheck:
    """The outcome of checking a file: its problems (none: `config` is the effective configuration)
    and where each key it or the command line sets came from (dotted key → 'file' or '--set')."""

    problems: list[ConfigProblem]
    sources: dict[str, str] = field(default_factory=dict)
    config: Config | None = None


def key_lines(text: str) -> dict[str, int]:
    """Dotted key (`cutpoints.cut_offset_m`) and table (`segmenter.learned`) → the 1-based line of
    TOML `text` where it is first written: bare and dotted keys, in `[table]` sections or at the top
    (quoted keys and inline tables' keys are not found; their problems name the file or the table)."""
    lines: dict[str, int] = {}
    table = ""
    for number, line in enumerate(text.splitlines(), start=1):
        header = _TABLE_HEADER.match(line)
        if header:
            table = ".".join(part.strip() for part in header.group(1).split("."))
            lines.setdefault(table, number)
            continue
        key = _KEY_LINE.match(line)
        if key:
            name = ".".join(part.strip() for part in key.group(1).split("."))
            lines.setdefault(f"{table}.{name}" if table else name, number)
    return lines


def leaf_keys(tree: dict[str, Any], prefix: str = "") -> Iterator[str]:
    """The dotted key of every value in a parsed TOML tree that is not itself a table."""
    for name, value in tree.items():
        if isinstance(value, dict):
            yield from leaf_keys(value, f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}"


def _path_key(path: Iterable[str | int]) -> str:
    """A JSON Schema error's path as the user writes the key: `camera.mount_xyz_m[1]`."""
    key = ""
    for part in path:
        key += f"[{part}]" if isinstance(part, int) else (f".{part}" if key else part)
    return key


def _schema_problems(data: dict[str, Any]) -> Iterator[tuple[str, str]]:
    """(dotted key, message) of every schema error of the TOML tree `data`; an unknown key or section
    gets the loader's message, with the nearest known name."""
    validator = jsonschema.Draft202012Validator(config_schema())
    for error in validator.iter_errors(data):
        table = _path_key(error.absolute_path)
        if error.validator == "additionalProperties" and isinstance(error.instance, dict):
            known = list(error.schema["properties"])
            for name in sorted(set(error.instance) - set(known)):
                if table:
                    yield f"{table}.{name}", unknown_option(table, name, known)
                else:
                    yield name, unknown_section(name, known)
        else:
            yield table, f"{table}: {error.message}"


def _semantic_problems(data: dict[str, Any]) -> Iterator[tuple[str, str]]:
    """(dotted key, message) of the settings classes' own checks, the first failing one of each section."""
    for name, table in data.items():
        try:
            config_from_dict({name: table})
        except ConfigError as exc:
            found = _MESSAGE_KEY.match(str(exc))
            yield (found.group(1) if found else name), str(exc)


def _without_index(key: str) -> str:
    """`camera.mount_xyz_m[1]` → `camera.mount_xyz_m`: the key a list item's problem is written at."""
    return re.sub(r"\[\d+\]", "", key)


def _where(key: str, path: Path | None, lines: dict[str, int], set_keys: set[str]) -> str:
    """`--set` when the key (or a table above it) came from the command line, else `FILE:LINE` of the key
    or of its nearest table written in the file, else `FILE` (`--set` without a file: only they set keys)."""
    bare = _without_index(key)
    parts = bare.split(".")
    prefixes = [".".join(parts[:n]) for n in range(len(parts), 0, -1)]
    if any(prefix in set_keys for prefix in prefixes) or any(k.startswith(f"{bare}.") for k in set_keys):
        return FROM_SET
    line = next((lines[prefix] for prefix in prefixes if prefix in lines), None)
    if path is None:
        return FROM_SET
    return f"{path}:{line}" if line else str(path)


def _read(path: Path) -> tuple[str, dict[str, Any]]:
    """The text of TOML file `path` and its tree; `ConfigError` naming the file when it cannot be read."""
    try:
        text = path.read_text(encoding="utf-8")
        return text, tomllib.loads(text)
    except FileNotFoundError:
        raise ConfigError("configuration file not found") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise ConfigError(f"cannot be read ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"not valid TOML ({exc})") from None


def check_config(path: str | Path | None, overrides: Iterable[Override] = ()) -> ConfigCheck:
    """Every problem of the configuration file `path` (None: no file, the defaults) with the command line's
    `overrides` applied, in the order of the file's lines; the effective configuration and each key's
    source when none."""
    path = None if path is None else Path(path)
    overrides = list(overrides)
    text = ""
    data: dict[str, Any] = {}  # no file: the defaults
    try:
        if path is not None:
            text, data = _read(path)
    except ConfigError as exc:
        at_line = _TOML_ERROR_LINE.search(str(exc))
        return ConfigCheck([ConfigProblem("", str(exc), f"{path}:{at_line.group(1)}" if at_line else str(path))])
    set_keys = {key for key, value in overrides for key in leaf_keys({key: value})}
    try:
        tree = with_overrides(data, overrides)
    except ConfigError as exc:
        return ConfigCheck([ConfigProblem("", str(exc), FROM_SET)])
    found = list(_schema_problems(tree)) or list(_semantic_problems(tree))
    if found:
        lines = key_lines(text)
        problems = [ConfigProblem(key, message, _where(key, path, lines, set_keys)) for key, message in found]
        problems.sort(key=lambda p: (p.where == FROM_SET, lines.get(_without_index(p.key), 0)))
        return ConfigCheck(problems)
    sources = {key: "file" for key in leaf_keys(data)} | {key: FROM_SET for key in set_keys}
    return ConfigCheck([], sources, config_from_dict(tree))
