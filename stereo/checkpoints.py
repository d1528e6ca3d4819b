"""Reading and writing EMCStereo checkpoints in the three layouts users have.

- **authors**: the EMCStereo release, a `torch.save` dict whose `model` entry holds the state_dict
  under `Backbone.`, `CostProcessor.aggregator.` and `DispProcessor.disp_processor.`.
- **psmnet**: PSMNet's own checkpoints (`feature_extraction.`, `dres0..4`, `classif1..3`, often a
  `module.` prefix, under `state_dict`), loaded into the no-attention variant.
- **ours**: `{"format": FORMAT, "config": ModelConfig, "model": state_dict}` with this package's names.

Every load is strict: each tensor is consumed, none is missing, every shape matches. Every
floating-point tensor is checked before it reaches the model: NaN or ±Inf, or a magnitude above
`MAX_ABS_WEIGHT` (what a flipped exponent bit produces), is refused with a `CheckpointError` naming
the tensor; float64 (or float16/bfloat16) tensors are cast to float32 with a warning that names them.

Wiring settings follow the source (`ModelConfig`): PSMNet checkpoints run with PSMNet's code
(`hourglass_wiring="psmnet"`, `align_corners=False`), the authors' with OpenStereo's
(`"openstereo"`, `True`), ours with what they store; ours written before these settings existed
carry `LEGACY_SETTINGS`, what this package ran then. `load_model(…, hourglass_wiring=…,
align_corners=…)` overrides either.

A file named as a registered release (`stereo.weights.REGISTRY`, e.g. `emcstereo_virtualtree_best.pth`)
must have the release's SHA-256, or `load_model` refuses it with a `WeightsMismatchError`;
`verify_sha256=False` (`--no-verify-weights`) loads a local file of that name anyway.
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import re
import tempfile
import warnings
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .model import EMCStereo, ModelConfig
from .weights import REGISTRY, WeightsInfo, cached_sha256, registered_as

FORMAT = "branchrange.emcstereo/1"

#: Largest |value| a trained EMCStereo tensor plausibly holds (BN running variances stay far below);
#: a flipped float32 exponent bit gives 1e19 … 3e38.
MAX_ABS_WEIGHT = 1e6
#: Wiring of each checkpoint source; "ours" stores its own.
SOURCE_SETTINGS: dict[str, dict[str, Any]] = {
    "authors": {"hourglass_wiring": "openstereo", "align_corners": True},
    "psmnet": {"hourglass_wiring": "psmnet", "align_corners": False},
}
#: What our checkpoints without these keys were run with (pre1 skip, align_corners=True).
LEGACY_SETTINGS: dict[str, Any] = {"hourglass_wiring": "psmnet", "align_corners": True}

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
    np._core.multiarray.scalar,  # type: ignore[attr-defined]  # private in numpy's stubs, public at run time
    np.dtype,
    *(type(np.dtype(t)) for t in (np.float16, np.float32, np.float64, np.int32, np.int64, np.bool_)),
]


class CheckpointError(ValueError):
    """A checkpoint that cannot be loaded; the message names the file and what was found."""


class WeightsMismatchError(CheckpointError):
    """A file named as a registered release whose contents are not the release's (corrupt, truncated or other)."""


def load_model(
    path: str | os.PathLike[str],
    device: str | torch.device = "cpu",
    *,
    hourglass_wiring: str | None = None,
    align_corners: bool | None = None,
    verify_sha256: bool = True,
    registry: Mapping[str, WeightsInfo] = REGISTRY,
) -> EMCStereo:
    """Build the right EMCStereo variant from a checkpoint in any supported layout, in eval mode.

    `hourglass_wiring` / `align_corners` override what the checkpoint's source implies (module docstring).
    A file named as an entry of `registry` is checked against its SHA-256 first (`verify_registered`)
    unless `verify_sha256` is False.
    """
    path = Path(path)
    if verify_sha256:
        verify_registered(path, registry)
    state, config, layout = read_checkpoint(path)
    try:
        if hourglass_wiring is not None:
            config = dataclasses.replace(config, hourglass_wiring=hourglass_wiring)
        if align_corners is not None:
            config = dataclasses.replace(config, align_corners=align_corners)
    except ValueError as exc:
        raise CheckpointError(f"{path}: {exc}") from exc
    model = EMCStereo.from_config(config)
    load_state_strict(model, state, source=f"{path} ({layout} layout)")
    return model.to(device).eval()


def verify_registered(path: Path, registry: Mapping[str, WeightsInfo] = REGISTRY) -> WeightsInfo | None:
    """The registry entry `path` is named after, once its SHA-256 matched; None for a file of another name.

    Raises `WeightsMismatchError` naming the file and both hashes when the contents differ.
    """
    info = registered_as(path, registry)
    if info is None or not path.is_file():  # a missing file is reported by the load itself
        return None
    digest = cached_sha256(path)
    if digest != info.sha256:
        raise WeightsMismatchError(
            f"{path}: SHA-256 {digest} does not match {info.sha256}, registered for {info.name} "
            f"({info.filename}); the file is corrupt, truncated or another checkpoint: fetch it again "
            f"(emcstereo weights fetch {info.name}), or load a local file of that name with "
            "--no-verify-weights (verify_sha256=False)"
        )
    return info


def read_checkpoint(path: Path) -> tuple[dict[str, torch.Tensor], ModelConfig, str]:
    """Return (state_dict in our names, variant config, layout name) of a checkpoint file."""
    raw = torch_load_checked(path)
    layout, state = _find_state_dict(raw, path)
    if layout == "psmnet":
        state = psmnet_to_ours(state)
    elif layout == "authors":
        state = authors_to_ours(state)
    state = checked_tensors(state, path)
    config = _config_from(raw, state, path) if layout == "ours" else variant_from_keys(state, SOURCE_SETTINGS[layout])
    return state, config, layout


def checked_tensors(state: Mapping[str, torch.Tensor], path: Path) -> dict[str, torch.Tensor]:
    """`state` with every floating tensor finite, of plausible magnitude and float32 (module docstring)."""
    checked, widened = {}, []
    for key, value in state.items():
        if value.is_floating_point():
            if not bool(torch.isfinite(value).all()):
                bad = int((~torch.isfinite(value)).sum())
                raise CheckpointError(
                    f"{path}: tensor {key} holds {bad} NaN/Inf value(s) of {value.numel()}; "
                    "the file is corrupt or the training diverged"
                )
            largest = float(value.abs().max()) if value.numel() else 0.0
            if largest > MAX_ABS_WEIGHT:
                raise CheckpointError(
                    f"{path}: tensor {key} holds |value| {largest:.3g}, above the plausible "
                    f"{MAX_ABS_WEIGHT:.0e} (a corrupt file, e.g. a flipped bit)"
                )
            if value.dtype != torch.float32:
                widened.append(f"{key} ({str(value.dtype).removeprefix('torch.')})")
                value = value.float()
        checked[key] = value
    if widened:
        warnings.warn(f"{path}: {len(widened)} tensor(s) cast to float32, e.g. {', '.join(widened[:3])}", stacklevel=3)
    return checked


def torch_load_checked(path: Path) -> Any:
    """`torch.load` (weights only, CPU) with every failure as a `CheckpointError` naming the file."""
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        with torch.serialization.safe_globals(_NUMPY_SCALAR_GLOBALS):
            return torch.load(path, map_location="cpu", weights_only=True)
    # Bytes that are not a torch file reach the legacy unpickler, which fails with whatever its
    # opcodes hit first (KeyError, ValueError, IndexError, …): all mean the same to the user.
    except (RuntimeError, EOFError, zipfile.BadZipFile, OSError, KeyError, ValueError, IndexError, TypeError) as exc:
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
    return key[len("module.") :] if key.startswith("module.") else key


def _config_from(raw: Mapping[str, Any], state: Mapping[str, torch.Tensor], path: Path) -> ModelConfig:
    stored = raw.get("config")
    if stored is None:
        return variant_from_keys(state, LEGACY_SETTINGS)
    if not isinstance(stored, Mapping):
        raise CheckpointError(f"{path}: `config` is a {type(stored).__name__}, expected a dict of model settings")
    try:
        return ModelConfig.from_mapping(stored, LEGACY_SETTINGS)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: bad `config`: {exc}") from exc


def variant_from_keys(state: Mapping[str, torch.Tensor], settings: Mapping[str, Any] = {}) -> ModelConfig:
    """Which modules a state_dict (our names) holds, and its disparity range; `settings` adds the wiring."""
    regression = state.get("regression.weight")
    try:
        return ModelConfig(
            ema=any(k.startswith("backbone.ema.") for k in state),
            msf=any(k.startswith("backbone.msf.") for k in state),
            coord=any(k.startswith("backbone.coord_att.") for k in state),
            max_disp=int(regression.numel()) if regression is not None else 192,
            **settings,
        )
    except ValueError as exc:
        raise CheckpointError(f"the checkpoint's tensors describe no buildable model: {exc}") from exc


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
            return dst + key[len(src) :]
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


def load_state_strict(model: EMCStereo, state: Mapping[str, torch.Tensor], source: str) -> None:
    """Copy every tensor into `model`, failing with one message that lists every mismatch."""
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = [
        f"{k}: file {tuple(state[k].shape)} vs model {tuple(expected[k].shape)}"
        for k in expected
        if k in state and state[k].shape != expected[k].shape
    ]
    if missing or unexpected or wrong:
        parts = [f"{source} does not fit EMCStereo{tuple(model.config.to_dict().values())}:"]
        for label, items in (("missing", missing), ("unexpected", unexpected), ("wrong shape", wrong)):
            if items:
                parts.append(f"{len(items)} {label} (e.g. {'; '.join(items[:3])})")
        raise CheckpointError(" ".join(parts))
    model.load_state_dict(dict(state), strict=True)


def save_checkpoint(
    model: EMCStereo, path: str | os.PathLike[str], *, layout: str = "ours", extra: Mapping[str, Any] | None = None
) -> Path:
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
