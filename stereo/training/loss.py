"""The deeply supervised disparity loss of the paper (reference facts §4).

total = Σ_k w_k · SmoothL1_β=1(clamp(pred_k), gt) over valid pixels (gt finite, 0 < gt < max_disp),
weights (0.5, 0.7, 1.0) — (0.25, 0.5, 1.0) in the SceneFlow recipe. Predictions are cast to fp32
and clamped to ±clamp_factor·max_disp; non-finite prediction pixels are dropped per head, a head
whose term is non-finite is skipped, an empty mask gives 0·Σpred (zero with a gradient path), and
a total above `loss_cap` is rescaled to `loss_cap` with a detached divisor (gradient direction kept).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

PAPER_WEIGHTS = (0.5, 0.7, 1.0)
SCENEFLOW_WEIGHTS = (0.25, 0.5, 1.0)


@dataclass(frozen=True)
class LossConfig:
    """Weights of the three heads, disparity range, prediction clamp factor and loss cap."""

    weights: tuple[float, ...] = PAPER_WEIGHTS
    max_disp: float = 192.0
    clamp_factor: float = 2.0
    loss_cap: float = 1000.0


def valid_disparity_mask(gt: torch.Tensor, max_disp: float) -> torch.Tensor:
    """Boolean mask `(B,H,W)` of pixels whose ground truth is finite and in (0, max_disp)."""
    return torch.isfinite(gt) & (gt > 0) & (gt < max_disp)


def disparity_loss(
    predictions: Sequence[torch.Tensor], gt: torch.Tensor, config: LossConfig = LossConfig()
) -> tuple[torch.Tensor, list[float]]:
    """Weighted smooth-L1 loss of the `(B,H,W)` predictions against `gt` `(B,H,W)` (px).

    Returns the scalar loss (fp32, differentiable) and the per-head terms as floats (NaN for a
    skipped head).
    """
    if len(predictions) != len(config.weights):
        raise ValueError(f"{len(predictions)} predictions but {len(config.weights)} loss weights {config.weights}")
    gt = gt.float()
    mask = valid_disparity_mask(gt, config.max_disp)
    limit = config.clamp_factor * config.max_disp
    total: torch.Tensor | None = None
    terms: list[float] = []
    for weight, pred in zip(config.weights, predictions):
        pred = pred.float().clamp(-limit, limit)
        head_mask = mask & torch.isfinite(pred)
        if not bool(head_mask.any()):
            terms.append(float("nan"))
            continue
        term = F.smooth_l1_loss(pred[head_mask], gt[head_mask], beta=1.0, reduction="mean")
        if not bool(torch.isfinite(term)):
            terms.append(float("nan"))
            continue
        terms.append(float(term.detach()))
        total = weight * term if total is None else total + weight * term
    if total is None:
        # Nothing to learn from: zero that still reaches every prediction so backward() works.
        total = 0.0 * sum(p.float().nan_to_num(0.0, 0.0, 0.0).sum() for p in predictions)
    if config.loss_cap > 0 and float(total.detach()) > config.loss_cap:
        total = total * (config.loss_cap / total.detach()).clamp(min=1e-6)
    return total, terms
