"""AdamW with the paper's weight-decay rule and the warm-up + per-iteration cosine schedule.

Decay applies only to trainable tensors with more than one dimension whose name is not a bias
(so no decay on biases, BatchNorm/GroupNorm weights or any 1-D tensor); frozen tensors are left
out of the optimiser. The learning-rate factor is (step+1)/warmup for the first `warmup` steps,
then a cosine from 1 to 0 over the remaining `total − warmup` steps, updated every iteration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn


def parameter_groups(model: nn.Module, weight_decay: float) -> list[dict]:
    """Two AdamW groups of the trainable parameters: decayed (≥2-D weights) and not (biases, 1-D)."""
    decay, no_decay = [], []
    for name, param in model.named_parameters():
        if not param.requires_grad:
            continue
        if param.ndim <= 1 or name.endswith(".bias"):
            no_decay.append(param)
        else:
            decay.append(param)
    if not decay and not no_decay:
        raise ValueError(f"{type(model).__name__} has no trainable parameter (everything is frozen)")
    return [
        {"params": decay, "weight_decay": weight_decay},
        {"params": no_decay, "weight_decay": 0.0},
    ]


def build_optimizer(
    model: nn.Module, lr: float, weight_decay: float, betas: tuple[float, float] = (0.9, 0.999)
) -> torch.optim.AdamW:
    """AdamW over the trainable parameters of `model` with the no-decay rule above."""
    return torch.optim.AdamW(parameter_groups(model, weight_decay), lr=lr, betas=betas)


@dataclass
class WarmupCosine:
    """LR factor of step `s`: linear warm-up (s+1)/warmup, then cosine to 0 at `total_steps`.

    A plain object (not a closure) so that `LambdaLR.state_dict()` stores it with the checkpoint.
    """

    warmup_steps: int
    total_steps: int

    def __call__(self, step: int) -> float:
        if step < self.warmup_steps:
            return (step + 1) / self.warmup_steps
        span = max(1, self.total_steps - self.warmup_steps)
        progress = min(1.0, (step - self.warmup_steps) / span)
        return 0.5 * (1.0 + math.cos(math.pi * progress))


def build_scheduler(
    optimizer: torch.optim.Optimizer, warmup_steps: int, total_steps: int
) -> torch.optim.lr_scheduler.LambdaLR:
    """Per-iteration warm-up + cosine schedule; call `.step()` after every optimiser step."""
    if total_steps <= 0 or warmup_steps < 0:
        raise ValueError(f"schedule needs total_steps > 0 and warmup_steps ≥ 0, got {total_steps}, {warmup_steps}")
    return torch.optim.lr_scheduler.LambdaLR(optimizer, WarmupCosine(warmup_steps, total_steps))
