"""Experiment configuration: TOML files validated into dataclasses.

A file has the sections `[model]` (the EMCStereo variant, `stereo.model.ModelConfig`), `[data]`,
`[optim]`, `[train]` and `[finetune]`; every key has a default, unknown keys and wrong types raise
`ConfigError` naming `section.key`. A file may start with `extends = "other.toml"` (relative to
itself): the other file is read first and this one's keys override it, which keeps the recipe
variants (e.g. the eight-way ablation) short.
Command-line overrides use the same dotted names (`train.epochs=3`).
"""

from __future__ import annotations

import dataclasses
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from stereo.model import ModelConfig
from stereo.training.loss import PAPER_WEIGHTS

DATASET_NAMES = ("virtualtree", "synthetic", "sceneflow", "kitti2012", "kitti2015", "eth3d", "middlebury")


class ConfigError(ValueError):
    """A configuration file or override that is not valid; the message names the key and the fix."""


@dataclass(frozen=True)
class DataSection:
    """Dataset, root folder, split rule and training-crop settings.

    `split`: "files" (VirtualTree split files `train_split`/`val_split`), "paper" (seeded 90/10 of
    every pair; the open datasets' rule) or "group" (whole groups held out, id from `group_pattern`).
    """

    dataset: str = "virtualtree"
    root: str = ""
    split: str = "files"
    train_split: str = "train"
    val_split: str = "val"
    val_fraction: float = 0.1
    split_seed: int = 0
    group_pattern: str = ""
    crop: tuple[int, ...] = (256, 512)
    color_jitter: bool = True
    num_workers: int = 8


@dataclass(frozen=True)
class OptimSection:
    """AdamW and the warm-up + cosine schedule."""

    lr: float = 5e-4
    weight_decay: float = 1e-4
    betas: tuple[float, ...] = (0.9, 0.999)
    warmup_steps: int = 500


@dataclass(frozen=True)
class TrainSection:
    """Loop, precision, loss, EMA, validation, checkpoint and logging settings.

    `ema_decay` 0 turns EMA off; `patience` 0 turns early stopping off; `max_steps` 0 means the
    full `epochs`; `checkpoint_every` 0 writes `last.pth` only at epoch ends.
    """

    epochs: int = 300
    batch_size: int = 4
    accumulate: int = 1
    precision: str = "fp16"
    grad_clip: float = 1.0
    loss_weights: tuple[float, ...] = PAPER_WEIGHTS
    clamp_factor: float = 2.0
    loss_cap: float = 1000.0
    ema_decay: float = 0.0
    patience: int = 50
    seed: int = 0
    out_dir: str = "runs/emcstereo"
    log_every: int = 10
    vis_count: int = 10
    checkpoint_every: int = 0
    max_steps: int = 0
    val_max_images: int = 0
    drop_last: bool = True


@dataclass(frozen=True)
class FinetuneSection:
    """Warm start: weights in our, the authors' or PSMNet's layout, and module prefixes to freeze."""

    weights: str = ""
    freeze: tuple[str, ...] = ()


@dataclass(frozen=True)
class ExperimentConfig:
    """A whole training / fine-tuning recipe."""

    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataSection = field(default_factory=DataSection)
    optim: OptimSection = field(default_factory=OptimSection)
    train: TrainSection = field(default_factory=TrainSection)
    finetune: FinetuneSection = field(default_factory=FinetuneSection)

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (tuples as lists), for logs and checkpoints."""
        tree = dataclasses.asdict(self)
        return {
            name: {k: list(v) if isinstance(v, tuple) else v for k, v in section.items()}
            for name, section in tree.items()
        }


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """`value` converted to the field type `hint`, or ConfigError naming `where`."""
    origin = typing.get_origin(hint)
    if origin is tuple:
        item_type = typing.get_args(hint)[0]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list of {item_type.__name__}, got {value!r}")
        return tuple(_coerce(v, item_type, f"{where}[{i}]") for i, v in enumerate(value))
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    raise ConfigError(f"{where}: unsupported field type {hint}")


def _section(cls: type, values: dict[str, Any], name: str) -> Any:
    """Build section dataclass `cls` from a TOML table, rejecting unknown keys and wrong types."""
    if not isinstance(values, dict):
        raise ConfigError(f"[{name}] must be a table, got {values!r}")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ConfigError(
            f"unknown key(s) {', '.join(f'{name}.{k}' for k in unknown)}; valid keys: {', '.join(sorted(known))}"
        )
    try:
        return cls(**{k: _coerce(v, hints[k], f"{name}.{k}") for k, v in values.items()})
    except ValueError as exc:  # a section's own range checks (e.g. ModelConfig's)
        raise ConfigError(f"[{name}] {exc}") from exc


def _merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """Recursive dict merge: tables merged key by key, everything else replaced."""
    out = dict(base)
    for key, value in override.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def read_toml_tree(path: Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The TOML tables of `path` with its `extends` chain resolved (base first)."""
    path = path.resolve()
    if path in _seen:
        raise ConfigError(f"{path}: `extends` forms a cycle through {', '.join(map(str, _seen))}")
    if not path.is_file():
        raise ConfigError(f"{path}: configuration file not found")
    try:
        tree = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    parent = tree.pop("extends", None)
    if parent is None:
        return tree
    if not isinstance(parent, str):
        raise ConfigError(f"{path}: `extends` must be a file name, got {parent!r}")
    return _merge(read_toml_tree(path.parent / parent, _seen + (path,)), tree)


def parse_override(text: str) -> dict[str, Any]:
    """`section.key=value` (value in TOML syntax, bare words taken as strings) → nested dict."""
    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise ConfigError(f"override {text!r}: expected section.key=value, e.g. train.epochs=3")
    dotted, raw = text.split("=", 1)
    section, key = dotted.strip().split(".", 1)
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return {section: {key: value}}


def build_config(tree: dict[str, Any], overrides: list[str] = ()) -> ExperimentConfig:
    """Validate nested tables (+ `section.key=value` overrides) into an ExperimentConfig."""
    for text in overrides:
        tree = _merge(tree, parse_override(text))
    sections = {f.name: f.type for f in dataclasses.fields(ExperimentConfig)}
    hints = typing.get_type_hints(ExperimentConfig)
    unknown = sorted(set(tree) - set(sections))
    if unknown:
        raise ConfigError(f"unknown section(s) {', '.join(unknown)}; valid sections: {', '.join(sections)}")
    config = ExperimentConfig(**{name: _section(hints[name], tree[name], name) for name in tree})
    validate(config)
    return config


def load_config(path: str | Path, overrides: list[str] = ()) -> ExperimentConfig:
    """Read, merge (`extends`), override and validate a TOML experiment file."""
    return build_config(read_toml_tree(Path(path)), list(overrides))


def validate(config: ExperimentConfig) -> None:
    """Cross-field checks the types alone cannot express."""
    data, train, optim = config.data, config.train, config.optim
    checks = [
        (data.dataset in DATASET_NAMES, f"data.dataset {data.dataset!r}: expected one of {', '.join(DATASET_NAMES)}"),
        (data.split in ("files", "paper", "group"), f"data.split {data.split!r}: expected files, paper or group"),
        (data.split != "group" or bool(data.group_pattern), 'data.group_pattern: required when data.split = "group"'),
        (
            len(data.crop) == 2 and min(data.crop) > 0 and all(c % 32 == 0 for c in data.crop),
            f"data.crop {list(data.crop)}: expected [height, width], positive multiples of 32 (≥ 256 for EMCStereo)",
        ),
        (
            train.precision in ("fp32", "fp16", "bf16"),
            f"train.precision {train.precision!r}: expected fp32, fp16 or bf16",
        ),
        (len(train.loss_weights) == 3, f"train.loss_weights {list(train.loss_weights)}: expected three weights"),
        (0.0 <= train.ema_decay < 1.0, f"train.ema_decay {train.ema_decay}: expected 0 (off) or a decay in (0, 1)"),
        (
            train.epochs > 0 and train.batch_size > 0 and train.accumulate > 0,
            "train.epochs, train.batch_size and train.accumulate must be positive",
        ),
        (len(optim.betas) == 2, f"optim.betas {list(optim.betas)}: expected two values"),
        (optim.lr > 0, f"optim.lr {optim.lr}: expected a positive learning rate"),
        (
            config.model.max_disp > 0 and config.model.max_disp % 16 == 0,
            f"model.max_disp {config.model.max_disp}: expected a positive multiple of 16 (the cost volume is "
            "at 1/4 resolution and the hourglasses halve it twice)",
        ),
    ]
    for ok, message in checks:
        if not ok:
            raise ConfigError(message)


def replace(config: ExperimentConfig, **sections: dict[str, Any]) -> ExperimentConfig:
    """A copy of `config` with some fields of some sections replaced, e.g. `train={"epochs": 2}`."""
    tree = config.to_dict()
    return build_config(_merge(tree, sections))


__all__ = [
    "ConfigError",
    "DataSection",
    "ExperimentConfig",
    "FinetuneSection",
    "OptimSection",
    "TrainSection",
    "build_config",
    "load_config",
    "parse_override",
    "replace",
]
