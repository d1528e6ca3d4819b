"""Reading and writing EMCStereo checkpoints in the three layouts users have.

- **authors**: the EMCStereo release, a `torch.save` dict whose `model` entry holds the state_dict
  under `Backbone.`, `CostProcessor.aggregator.` and `DispProcessor.disp_processor.`.
- **psmnet**: PSMNet's own checkpoints (`feature_extraction.`, `dres0..4`, `classif1..3`, often a
  `module.` prefix, under `state_dict`), loaded into the no-attention variant.
- **ours**: `{"format": FORMAT, "config": ModelConfig, "model": state_dict}` with this package's names.

Every load is strict: each tensor is consumed, none is missing, every shape matches.
"""
from __future__ import annotations

import os
import pickle
import re
import tempfile
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .model import EMCStereo, ModelConfig

FORMAT = "branchrange.emcstereo/1"

#: Our top-level module names ↔ the authors' prefixes.
_AUTHORS_PREFIXES = (
    ("backbone.", "Backbone."),
    ("aggregation.", "CostProcessor.aggregator."),
    ("regression.", "DispProcessor.disp_processor.disp_regression."),
)

#: PSMNet keeps ReLUs as separate Sequential entries; these rules renumber its indices.
_PSMNET_RENAMES = (
    (r"^feature_extraction\.firstconv\.([024])\.", lambda m: f"backbone.firstconv.{int(m[1]) // 2}."),
    (r"^feature_extraction\.(layer\d\.\d+)\.conv1\.0\.", r"backbone.\1.conv1."),
    (r"^feature_extraction\.lastconv\.2\.", "backbone.lastconv.1."),
    (r"^feature_extraction\.", "backbone."),
    (r"^(dres[01])\.([02])\.", lambda m: f"aggregation.{m[1]}.{int(m[2]) // 2}."),
    (r"^(dres[234])\.(conv[134])\.0\.", r"aggregation.\1.\2."),
    (r"^(classif\d)\.2\.", r"aggregation.\1.1."),
    (r"^(dres\d|classif\d)\.", r"aggregation.\1."),
)

#: Tensors of the authors' model that PSMNet lacks, set so the output is PSMNet's.
_PSMNET_MISSING_BIASES = ("backbone.layer2.0.downsample.0.bias", "backbone.layer3.0.downsample.0.bias")


#: Training checkpoints often carry metric dicts of numpy scalars; these rebuild plain numbers only.
_NUMPY_SCALAR_GLOBALS = [
    np._core.multiarray.scalar, np.dtype,
    *(type(np.dtype(t)) for t in (np.float16, np.float32, np.float64, np.int32, np.int64, np.bool_)),
]


class CheckpointError(ValueError):
    """A checkpoint that cannot be loaded; the message names the file and what was found."""


def load_model(path: str | os.PathLike[str], device: str | torch.device = "cpu") -> EMCStereo:
    """Build the right EMCStereo variant from a checkpoint in any supported layout, in eval mode."""
    path = Path(path)
    state, config, layout = read_checkpoint(path)
    model = EMCStereo(**config.to_dict())
    load_state_strict(model, state, source=f"{path} ({layout} layout)")
    return model.to(device).eval()


def read_checkpoint(path: Path) -> tuple[dict[str, torch.Tensor], ModelConfig, str]:
    """Return (state_dict in our names, variant config, layout name) of a checkpoint file."""
    raw = _torch_load(path)
    layout, state = _find_state_dict(raw, path)
    if layout == "psmnet":
        state = psmnet_to_ours(state)
    elif layout == "authors":
        state = authors_to_ours(state)
    config = _config_from(raw, state) if layout == "ours" else variant_from_keys(state)
    return state, config, layout


def _torch_load(path: Path) -> Any:
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        with torch.serialization.safe_globals(_NUMPY_SCALAR_GLOBALS):
            return torch.load(path, map_location="cpu", weights_only=True)
    # Bytes that are not a torch file reach the legacy unpickler, which fails with whatever its
    # opcodes hit first (KeyError, ValueError, IndexError, …): all mean the same to the user.
    except (RuntimeError, EOFError, zipfile.BadZipFile, OSError, KeyError, ValueError, IndexError,
            TypeError) as exc:
        raise CheckpointError(
            f"{path}: not a readable torch checkpoint ({path.stat().st_size} bytes; truncated or "
            f"corrupt?): {_essence(exc)}"
        ) from exc
    except pickle.UnpicklingError as exc:  # a pickle that needs code to load: never executed here
        raise CheckpointError(f"{path}: not a weights-only torch checkpoint: {_essence(exc)}") from exc


def _essence(exc: BaseException) -> str:
    """The one line of torch's multi-line load errors that says what was wrong."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    for line in lines:
        if "Unsupported global" in line or "WeightsUnpickler error" in line:
            return line
    return lines[0] if lines else type(exc).__name__


def _find_state_dict(raw: Any, path: Path) -> tuple[str, dict[str, torch.Tensor]]:
    if not isinstance(raw, Mapping):
        raise CheckpointError(f"{path}: expected a dict of tensors, found {type(raw).__name__}")
    if raw.get("format") == FORMAT:
        return "ours", _tensors(raw["model"], path)
    for entry in ("model", "state_dict"):
        if isinstance(raw.get(entry), Mapping):
            raw = raw[entry]
            break
    state = {_strip_module(k): v for k, v in _tensors(raw, path).items()}
    keys = list(state)
    if any(k.startswith("Backbone.") for k in keys):
        return "authors", state
    if any(k.startswith("feature_extraction.") for k in keys):
        return "psmnet", state
    if any(k.startswith("backbone.") for k in keys):
        return "ours", state
    sample = ", ".join(keys[:3]) or "no keys"
    raise CheckpointError(
        f"{path}: unrecognised checkpoint ({len(keys)} tensors, e.g. {sample}); expected the "
        "authors' layout (Backbone.…), PSMNet's (feature_extraction.…) or ours"
    )


def _tensors(mapping: Any, path: Path) -> dict[str, torch.Tensor]:
    if not isinstance(mapping, Mapping):
        raise CheckpointError(f"{path}: the state_dict entry is a {type(mapping).__name__}, not a dict")
    bad = [k for k, v in mapping.items() if not isinstance(v, torch.Tensor)]
    if bad:
        raise CheckpointError(f"{path}: entries that are not tensors: {', '.join(map(str, bad[:5]))}")
    return dict(mapping)


def _strip_module(key: str) -> str:
    return key[len("module."):] if key.startswith("module.") else key


def _config_from(raw: Mapping[str, Any], state: Mapping[str, torch.Tensor]) -> ModelConfig:
    stored = raw.get("config")
    return ModelConfig(**stored) if isinstance(stored, Mapping) else variant_from_keys(state)


def variant_from_keys(state: Mapping[str, torch.Tensor]) -> ModelConfig:
    """Which modules a state_dict (our names) holds, and its disparity range."""
    regression = state.get("regression.weight")
    return ModelConfig(
        ema=any(k.startswith("backbone.ema.") for k in state),
        msf=any(k.startswith("backbone.msf.") for k in state),
        coord=any(k.startswith("backbone.coord_att.") for k in state),
        max_disp=int(regression.numel()) if regression is not None else 192,
    )


def authors_to_ours(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rename an authors'-layout state_dict to this package's module names."""
    return {_swap_prefix(k, to_ours=True): v for k, v in state.items()}


def ours_to_authors(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rename our state_dict to the authors' layout, so their tools can read our checkpoints."""
    return {_swap_prefix(k, to_ours=False): v for k, v in state.items()}


def _swap_prefix(key: str, *, to_ours: bool) -> str:
    for ours, theirs in _AUTHORS_PREFIXES:
        src, dst = (theirs, ours) if to_ours else (ours, theirs)
        if key.startswith(src):
            return dst + key[len(src):]
    raise CheckpointError(f"state_dict key {key!r} belongs to no known part of the model")


def psmnet_to_ours(state: Mapping[str, torch.Tensor], max_disp: int = 192) -> dict[str, torch.Tensor]:
    """Rename a PSMNet state_dict and add the three tensors it lacks (zero biases, 0..D−1)."""
    renamed = {}
    for key, value in state.items():
        new = key
        for pattern, replacement in _PSMNET_RENAMES:
            new, hits = re.subn(pattern, replacement, new)
            if hits:
                break
        renamed[new] = value
    for key in _PSMNET_MISSING_BIASES:
        weight = renamed.get(key.replace(".bias", ".weight"))
        if weight is not None:
            renamed.setdefault(key, torch.zeros(weight.shape[0], dtype=weight.dtype))
    renamed.setdefault("regression.weight", torch.arange(max_disp, dtype=torch.float32).reshape(1, 1, -1, 1, 1))
    return renamed


def load_state_strict(model: torch.nn.Module, state: Mapping[str, torch.Tensor], source: str) -> None:
    """Copy every tensor into `model`, failing with one message that lists every mismatch."""
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = [
        f"{k}: file {tuple(state[k].shape)} vs model {tuple(expected[k].shape)}"
        for k in expected if k in state and state[k].shape != expected[k].shape
    ]
    if missing or unexpected or wrong:
        parts = [f"{source} does not fit EMCStereo{tuple(model.config.to_dict().values())}:"]
        for label, items in (("missing", missing), ("unexpected", unexpected), ("wrong shape", wrong)):
            if items:
                parts.append(f"{len(items)} {label} (e.g. {'; '.join(items[:3])})")
        raise CheckpointError(" ".join(parts))
    model.load_state_dict(dict(state), strict=True)


def save_checkpoint(model: EMCStereo, path: str | os.PathLike[str], *, layout: str = "ours",
                    extra: Mapping[str, Any] | None = None) -> Path:
    """Write the model atomically, in our layout or the authors' (`{"model": …}`)."""
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    if layout == "ours":
        payload: dict[str, Any] = {"format": FORMAT, "config": model.config.to_dict(), "model": state}
    elif layout == "authors":
        payload = {"model": ours_to_authors(state)}
    else:
        raise ValueError(f"unknown checkpoint layout {layout!r}; use 'ours' or 'authors'")
    payload.update(extra or {})
    return atomic_torch_save(payload, Path(path))


def atomic_torch_save(payload: Any, path: Path) -> Path:
    """torch.save to a temporary file beside `path`, then rename: never a half-written file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(fd)
    try:
        torch.save(payload, tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
