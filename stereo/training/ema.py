"""Exponential moving average of a model's weights (the SceneFlow recipe's EMA, decay 0.9995).

After each optimiser step: shadow ← decay·shadow + (1 − decay)·weight for floating-point
parameters and buffers; integer buffers (BatchNorm's batch counter) are copied. Validation and
the best checkpoint use the shadow weights when EMA is on.
"""

from __future__ import annotations

import copy

import torch
from torch import nn


def unwrap(model: nn.Module) -> nn.Module:
    """The module inside a DistributedDataParallel / DataParallel wrapper, or the model itself."""
    return model.module if hasattr(model, "module") else model


class ModelEMA:
    """A frozen copy of a model whose weights trail the live model's by an exponential average."""

    def __init__(self, model: nn.Module, decay: float) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"EMA decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.module = copy.deepcopy(unwrap(model)).eval()
        for param in self.module.parameters():
            param.requires_grad_(False)

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Blend the live weights of `model` into the shadow copy."""
        live = unwrap(model).state_dict()
        for name, shadow in self.module.state_dict().items():
            value = live[name].detach()
            if shadow.dtype.is_floating_point:
                shadow.mul_(self.decay).add_(value.to(shadow.dtype), alpha=1.0 - self.decay)
            else:
                shadow.copy_(value)

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The shadow weights (same keys as the model's state_dict)."""
        return {k: v.detach().clone() for k, v in self.module.state_dict().items()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Restore shadow weights saved by `state_dict`."""
        self.module.load_state_dict(state, strict=True)
