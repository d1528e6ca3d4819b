"""BranchRange's one configuration file: `Config` gathers the sections, each the settings dataclass of the code that
reads it, and `load_config` reads the TOML file into it.

| section | dataclass | used by |
|---|---|---|
| `[camera]` | `branchrange.config.sections.CameraConfig` | the daemon's frame source, its mount and watchdog |
| `[stereo]` | `branchrange.core.pipeline.StereoConfig` | `Pipeline.backend` (`make_backend`), roi or full mode |
| `[roi]` | `branchrange.core.roi.RoiConfig` | `branchrange.core.roi.CoarseToFine`, the region budget |
| `[cutpoints]` | `branchrange.core.cutpoints.CutPointConfig` | cut-point estimation, target choice, tracking on/off |
| `[branch_tracking]` | `branchrange.core.tracking.TrackerConfig` | the per-frame branch ids (`BranchTracker`) |
| `[masks]` | `branchrange.core.masks.MaskConfig` | how mask files and arrays are read |
| `[segmenter]` | `branchrange.core.segmentation.choose.SegmenterConfig` (+ sub-tables) | `SegmenterConfig.build` |
| `[mavlink]` | `branchrange.config.sections.MavlinkConfig` | `branchrange.onboard.mavlink.MavlinkRelay` |
| `[tracking]` | `branchrange.config.sections.TrackingConfig` | the world-frame target tracks (`world_tracks`) |
| `[api]` | `branchrange.config.sections.ApiConfig` | the HTTP service |
| `[log]` | `branchrange.config.sections.LogConfig` | the results log and status reports |
| `[shedding]` | `branchrange.config.sections.SheddingConfig` | the daemon's load shedding |

The per-frame core never imports this module: the pipeline's sections reach it together as
`pipeline_config(cfg)`, which hands over the section objects themselves. Every option has a default, so an empty
file is a valid configuration. Every option can be set in the file and on the command line (`--set
section.key=value`, a TOML value; `--set segmenter.structure.max_range_m=3`); an unknown key, a value of the wrong
type or out of range raises `ConfigError` naming the key (`mavlink.send_rate_hz`) and what was expected. Examples
live in `deploy/*.toml`.

To add an option: add a typed field with a default to its section's dataclass, its plain range once to the class's
`limits` (a `branchrange.core.settings_check.Limit` with its `expected` message), a rule no `Limit` can state to
its `checks()`, and say what it does in a bullet of the class docstring (`branchrange.config.descriptions`). The
loader reads the field list; a field whose type is itself a settings dataclass is a sub-table. The JSON Schema that
editors check the file with and the reference `docs/configuration.md` are generated from the same classes
(`branchrange config schema`, `branchrange config reference`); tests say when they need regenerating.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import tomllib
import typing
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from branchrange.config.sections import (
    ApiConfig,
    CameraConfig,
    LogConfig,
    MavlinkConfig,
    SheddingConfig,
    TrackingConfig,
)
from branchrange.core.cutpoints import CutPointConfig
from branchrange.core.masks import MaskConfig
from branchrange.core.pipeline import Pipeline, PipelineConfig, StereoConfig
from branchrange.core.roi import RoiConfig
from branchrange.core.segmentation.choose import SegmenterConfig
from branchrange.core.settings_check import ConfigError, check_calibration
from branchrange.core.tracking import TrackerConfig
from camera.sources import SourceError


@dataclass(frozen=True)
class Config:
    """The whole configuration, one dataclass per TOML section."""

    camera: CameraConfig = field(default_factory=CameraConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    roi: RoiConfig = field(default_factory=RoiConfig)
    cutpoints: CutPointConfig = field(default_factory=CutPointConfig)
    branch_tracking: TrackerConfig = field(default_factory=TrackerConfig)
    masks: MaskConfig = field(default_factory=MaskConfig)
    segmenter: SegmenterConfig = field(default_factory=SegmenterConfig)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    api: ApiConfig = field(default_factory=ApiConfig)
    log: LogConfig = field(default_factory=LogConfig)
    shedding: SheddingConfig = field(default_factory=SheddingConfig)


#: A command-line override: the dotted key (`stereo.max_disp`, `segmenter.structure.max_range_m`) and its value.
Override = tuple[str, Any]


def did_you_mean(word: str, known: Iterable[str]) -> str:
    """'; did you mean `port`?' for the known name nearest a mistyped `word` ('' when none is near):
    a typo on the drone is found by reading the message, not the documentation."""
    near = difflib.get_close_matches(word, list(known), n=1)
    return f"; did you mean `{near[0]}`?" if near else ""


def unknown_option(table: str, key: str, known: Iterable[str]) -> str:
    """The message for `key` that the table `[table]` does not take: what it takes, and the nearest name."""
    known = list(known)
    return f"{table}.{key}: unknown option; [{table}] takes {', '.join(known)}{did_you_mean(key, known)}"


def unknown_section(name: str, known: Iterable[str]) -> str:
    """The message for a section `[name]` the file does not take: the sections it takes, and the nearest."""
    known = list(known)
    return f"[{name}]: unknown section; the file takes {', '.join(f'[{s}]' for s in known)}{did_you_mean(name, known)}"


def _wrong_type(key: str, value: Any, expected: str) -> ConfigError:
    return ConfigError(f"{key} = {value!r}: expected {expected}")


def _coerce(key: str, value: Any, annotation: Any) -> Any:
    """Check one TOML value against a field's type; ints are accepted where floats are expected,
    a table where the field is itself a settings dataclass."""
    if isinstance(annotation, type) and dataclasses.is_dataclass(annotation):
        return _table(annotation, key, value)
    if annotation is bool:
        if not isinstance(value, bool):
            raise _wrong_type(key, value, "true or false")
        return value
    if annotation is int:
        if not isinstance(value, int) or isinstance(value, bool):
            raise _wrong_type(key, value, "an integer")
        return value
    if annotation is float:
        if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)):
            raise _wrong_type(key, value, "a finite number")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise _wrong_type(key, value, "a string")
        return value
    if typing.get_origin(annotation) is tuple and typing.get_args(annotation)[1:] == (Ellipsis,):
        if not isinstance(value, list):
            raise _wrong_type(key, value, "a list")
        item = typing.get_args(annotation)[0]
        return tuple(_coerce(f"{key}[{i}]", v, item) for i, v in enumerate(value))
    if typing.get_origin(annotation) is tuple:
        items = typing.get_args(annotation)
        if not (isinstance(value, list) and len(value) == len(items)):
            raise _wrong_type(key, value, f"a list of {len(items)} numbers")
        return tuple(_coerce(f"{key}[{i}]", v, t) for i, (v, t) in enumerate(zip(value, items)))
    raise TypeError(f"config field {key} has an unsupported type {annotation!r}")


def _table(cls: type, name: str, table: Any) -> Any:
    """Settings dataclass `cls` from the TOML table `[name]`: unknown keys refused, every value
    type-checked, then the class's own range checks; every error a `ConfigError` naming the key."""
    if not isinstance(table, dict):
        raise _wrong_type(name, table, f"a table [{name}]")
    hints = typing.get_type_hints(cls)
    known = sorted(f.name for f in dataclasses.fields(cls))
    unknown = sorted(set(table) - set(known))
    if unknown:
        raise ConfigError(unknown_option(name, unknown[0], known))
    values = {key: _coerce(f"{name}.{key}", value, hints[key]) for key, value in table.items()}
    try:
        return cls(**values)
    except ConfigError:
        raise
    except ValueError as exc:  # the range check of a section defined beside its code (CutPointConfigError, …)
        raise ConfigError(str(exc)) from None


def config_from_dict(data: dict[str, Any]) -> Config:
    """Validate a parsed TOML document into a `Config`; raises `ConfigError` naming the key."""
    sections = typing.get_type_hints(Config)
    unknown = sorted(set(data) - set(sections))
    if unknown:
        raise ConfigError(unknown_section(unknown[0], sections))
    return Config(**{name: _table(sections[name], name, table) for name, table in data.items()})


def parse_override(text: str) -> Override:
    """`SECTION.KEY=VALUE` (`--set`) → (dotted key, value): the value in TOML syntax
    (`128`, `true`, `[0, -10, 0]`, `"text"`), a bare word taken as a string (`--set stereo.backend=sgbm`)."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or "." not in key or not all(key.split(".")):
        raise ConfigError(f"--set {text!r}: expected SECTION.KEY=VALUE, e.g. --set stereo.max_disp=128")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return key, value


def with_overrides(data: dict[str, Any], overrides: Iterable[Override]) -> dict[str, Any]:
    """A copy of the TOML tree `data` with each (dotted key, value) set in it, later ones winning."""
    tree: dict[str, Any] = {name: dict(table) if isinstance(table, dict) else table for name, table in data.items()}
    for key, value in overrides:
        *tables, last = key.split(".")
        node = tree
        for depth, name in enumerate(tables):
            child = node.get(name, {})
            if not isinstance(child, dict):
                raise _wrong_type(".".join(tables[: depth + 1]), child, f"a table (--set {key}=…)")
            node[name] = node = dict(child)
        node[last] = value
    return tree


def load_config(path: str | Path | None, overrides: Iterable[Override] = ()) -> Config:
    """Read and validate a TOML configuration file (`None`: the defaults), then the command line's
    `overrides` ((dotted key, value), e.g. from `parse_override`; later ones win)."""
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
            config_from_dict(data)  # the file's own errors name the file
        except FileNotFoundError:
            raise ConfigError(f"{path}: configuration file not found") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML ({exc})") from None
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
    return config_from_dict(with_overrides(data, overrides))


def pipeline_config(cfg: Config) -> PipelineConfig:
    """The `branchrange.core.pipeline.PipelineConfig` of `cfg`: its pipeline sections themselves."""
    return PipelineConfig(
        stereo=cfg.stereo,
        roi=cfg.roi,
        cutpoints=cfg.cutpoints,
        tracker=cfg.branch_tracking,
        masks=cfg.masks,
        segmenter=cfg.segmenter,
    )


def pipeline_for(cfg: Config, calibration: Any) -> Any:
    """The `Pipeline` that the pipeline's sections of `cfg` describe, for a source's calibration,
    with its stereo backend already built: a calibration outside the physical ranges, a missing
    checkpoint or a max_disp the backend cannot use fails here, at start-up, rather than as a
    rejected frame on every frame.

    Raises `SourceError` naming `camera.source` when the source brought no calibration, `RangeError`
    for a focal length or baseline out of range, and the backend's `ValueError`
    (`BackendConfigError`, `CheckpointError`) when it cannot be built.
    """
    if calibration is None:
        raise SourceError(f"{cfg.camera.source}: no calibration; set camera.calibration")
    check_calibration(calibration, tuple(calibration.image_size), f"{cfg.camera.source}: calibration")
    pipeline = Pipeline(pipeline_config(cfg), calibration=calibration)
    _ = pipeline.backend  # the property builds it
    return pipeline
