"""Warm starts and frozen modules for fine-tuning.

A run can start from weights in any layout `stereo.load_model` reads — ours, the authors' release
or PSMNet's (loaded into the no-attention variant) — which the authors' own training script
cannot do. Freezing takes module-name prefixes (e.g. `backbone`): their parameters stop
receiving gradients, are left out of the optimiser, and their BatchNorm layers stay in eval mode
so their running statistics do not drift.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from torch import nn

import stereo
from stereo.model import EMCStereo, ModelConfig
from stereo.training.config import ConfigError


def warm_start(weights: str | Path, expected: ModelConfig | None = None) -> EMCStereo:
    """EMCStereo with the weights of `weights` (any supported layout), in train mode.

    When `expected` is given, the checkpoint's variant (modules, max_disp) must match it; its
    wiring settings (`hourglass_wiring`, `align_corners`) stay the checkpoint's, the ones its
    weights were trained with.
    """
    model = stereo.load_model(weights)
    structure = ("ema", "msf", "coord", "max_disp")
    if expected is not None and any(getattr(model.config, k) != getattr(expected, k) for k in structure):
        raise ConfigError(
            f"{weights}: holds the variant {model.config.to_dict()} but [model] asks for {expected.to_dict()}; "
            "set [model] to the checkpoint's variant"
        )
    return model.train()


def freeze(model: nn.Module, prefixes: Sequence[str]) -> list[str]:
    """Stop gradients of every parameter under the named modules; return the frozen parameter names."""
    modules = dict(model.named_modules())
    missing = [p for p in prefixes if p not in modules]
    if missing:
        top = ", ".join(name for name, _ in model.named_children())
        raise ConfigError(f"finetune.freeze: no module named {', '.join(missing)}; top-level modules are {top}")
    frozen = []
    for name, param in model.named_parameters():
        if any(name == p or name.startswith(p + ".") for p in prefixes):
            param.requires_grad_(False)
            frozen.append(name)
    return frozen


def keep_frozen_in_eval(model: nn.Module, prefixes: Sequence[str]) -> None:
    """Put the frozen modules back into eval mode (call after every `model.train()`)."""
    modules = dict(model.named_modules())
    for prefix in prefixes:
        modules[prefix].eval()
