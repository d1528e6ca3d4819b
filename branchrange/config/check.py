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
class KeyPlaces:
    """Where the keys of a checked file were written: the file, its keys' lines (`key_lines`) and the keys
    the command line set; `of(key)` says where a problem of `key` is to be looked for."""

    path: Path | None
    lines: dict[str, int]
    set_keys: set[str]

    def of(self, key: str) -> str:
        """`--set`, `FILE:LINE` or `FILE` for dotted `key` (`_where`)."""
        return _where(key, self.path, self.lines, self.set_keys)

    def order(self, problem: ConfigProblem) -> tuple[bool, int]:
        """Where `problem` is in reading order: the file's lines first (its table's line for a key it does not
        write), then the command line's."""
        return problem.where == FROM_SET, self.lines.get(_without_index(problem.key), 0)


@dataclass(frozen=True)
class ConfigCheck:
    """The outcome of checking a file: its problems (none: `config` is the effective configuration)
    and where each key it or the command line sets came from (dotted key → 'file' or '--set'); once the
    file could be read, its TOML tree with the overrides applied and where each key was written."""

    problems: list[ConfigProblem]
    sources: dict[str, str] = field(default_factory=dict)
    config: Config | None = None
    tree: dict[str, Any] = field(default_factory=dict)
    places: KeyPlaces | None = None


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


def _failing_key(section: str, table: Any) -> tuple[str, str] | None:
    """(dotted key, message) of the first failing check of the section `[section]` = `table`; None: it passes."""
    try:
        config_from_dict({section: table})
    except ConfigError as exc:
        found = _MESSAGE_KEY.match(str(exc))
        return (found.group(1) if found else section), str(exc)
    return None


def _without(tree: dict[str, Any], key: str) -> dict[str, Any]:
    """A copy of the TOML tree `tree` without the value of dotted `key` (its tables copied along the way)."""
    *tables, last = key.split(".")
    copy = dict(tree)
    node = copy
    for name in tables:
        node[name] = node = dict(node[name])
    del node[last]
    return copy


def _blamed(tree: dict[str, Any], key: str, message: str, set_keys: set[str]) -> tuple[str, str]:
    """(key, message) of a failed check on `key`. A check between keys is attached to one of them, which may
    not be the one written wrong: when `key` holds its default (`--set cutpoints.min_range_m=20` against the
    default `max_range_m = 10`), or comes from the file while a key of its table came from `--set`, the
    written key without which the check passes is the one to name, and its place the one to show."""
    written = set(leaf_keys(tree))
    if key in set_keys:
        return key, message
    suspects, origin = (set_keys, "the file's") if key in written else (written, "its default")
    section, table = key.partition(".")[0], key.rpartition(".")[0]
    for other in sorted(k for k in suspects if k.rpartition(".")[0] == table and k != key):
        if _failing_key(section, _without(tree, other).get(section, {})) is None:
            value = _value_of(tree, other)
            return other, f"{other} = {value!r} conflicts with {key} ({origin}): {message}"
    return key, message


def _value_of(tree: dict[str, Any], key: str) -> Any:
    """The value of dotted `key` in the TOML tree `tree`."""
    node: Any = tree
    for name in key.split("."):
        node = node[name]
    return node


def _semantic_problems(data: dict[str, Any], set_keys: set[str]) -> Iterator[tuple[str, str]]:
    """(dotted key, message) of the settings classes' own checks, the first failing one of each section
    (`_blamed`: the key to name when the check is between keys; `set_keys` came from the command line)."""
    for name, table in data.items():
        failed = _failing_key(name, table)
        if failed is not None:
            yield _blamed(data, *failed, set_keys)


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
    places = KeyPlaces(path, key_lines(text), set_keys)
    found = list(_schema_problems(tree)) or list(_semantic_problems(tree, set_keys))
    if found:
        problems = [ConfigProblem(key, message, places.of(key)) for key, message in found]
        problems.sort(key=places.order)
        return ConfigCheck(problems, tree=tree, places=places)
    sources = {key: "file" for key in leaf_keys(data)} | {key: FROM_SET for key in set_keys}
    return ConfigCheck([], sources, config_from_dict(tree), tree, places)
