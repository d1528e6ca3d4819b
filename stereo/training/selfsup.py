"""Self-supervised fine-tuning on unlabelled rectified pairs (no ground truth needed).

For a team with its own ZED recordings: the network's left disparity d warps the right image into
the left view, I_r(x − d, y); the loss is the photometric error between that and the left image,
α·(1 − SSIM)/2 + (1 − α)·|ΔI| with α = 0.85, plus an edge-aware smoothness term on the
mean-normalised disparity (|∂d|·e^{−|∂I|}). Pixels are ignored where the warp leaves the image or
where left–right consistency fails (occlusions): the right disparity, predicted by the same network
on the mirrored pair, warped into the left view must agree with d within max(τ, 5 % of d).
The three deeply supervised outputs are weighted as in supervised training.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from stereo.datasets.transforms import IMAGENET_MEAN, IMAGENET_STD
from stereo.evaluation import autocast_context
from stereo.training.finetune import keep_frozen_in_eval
from stereo.training.trainer import Trainer


@dataclass(frozen=True)
class SelfSupConfig:
    """Weights and thresholds of the self-supervised loss."""

    ssim_weight: float = 0.85
    smoothness_weight: float = 0.1
    lr_check: bool = True
    lr_abs_threshold: float = 1.0
    lr_rel_threshold: float = 0.05


def denormalize(image: torch.Tensor) -> torch.Tensor:
    """ImageNet-normalised `(B,3,H,W)` → RGB in [0, 1]."""
    mean = image.new_tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = image.new_tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return image * std + mean


def warp_right_to_left(right: torch.Tensor, disparity: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample `right` `(B,C,H,W)` at (x − d, y) for left disparity `d` `(B,H,W)` px.

    Returns the warped image `(B,C,H,W)` and a `(B,1,H,W)` mask of samples inside the right image.
    """
    _, _, height, width = right.shape
    xs = torch.arange(width, device=right.device, dtype=disparity.dtype).view(1, 1, width)
    ys = torch.arange(height, device=right.device, dtype=disparity.dtype).view(1, height, 1)
    source_x = xs - disparity
    grid = torch.stack(
        [2.0 * source_x / max(width - 1, 1) - 1.0, (2.0 * ys / max(height - 1, 1) - 1.0).expand_as(source_x)], dim=-1
    )
    warped = F.grid_sample(right, grid.to(right.dtype), mode="bilinear", padding_mode="border", align_corners=True)
    inside = ((source_x >= 0) & (source_x <= width - 1)).unsqueeze(1)
    return warped, inside


def ssim_dissimilarity(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Per-pixel (1 − SSIM)/2 over 3×3 windows, channel-averaged: `(B,1,H,W)` in [0, 1]."""
    c1, c2 = 0.01**2, 0.03**2
    pad = lambda t: F.pad(t, (1, 1, 1, 1), mode="reflect")  # noqa: E731
    mu_x, mu_y = F.avg_pool2d(pad(x), 3, 1), F.avg_pool2d(pad(y), 3, 1)
    sigma_x = F.avg_pool2d(pad(x * x), 3, 1) - mu_x**2
    sigma_y = F.avg_pool2d(pad(y * y), 3, 1) - mu_y**2
    sigma_xy = F.avg_pool2d(pad(x * y), 3, 1) - mu_x * mu_y
    ssim = ((2 * mu_x * mu_y + c1) * (2 * sigma_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sigma_x + sigma_y + c2))
    return ((1 - ssim) / 2).clamp(0, 1).mean(1, keepdim=True)


def photometric_error(target: torch.Tensor, warped: torch.Tensor, ssim_weight: float = 0.85) -> torch.Tensor:
    """α·(1 − SSIM)/2 + (1 − α)·mean|target − warped|, per pixel `(B,1,H,W)`."""
    l1 = (target - warped).abs().mean(1, keepdim=True)
    return ssim_weight * ssim_dissimilarity(target, warped) + (1 - ssim_weight) * l1


def edge_aware_smoothness(disparity: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """Mean |∂x d̂|·e^{−|∂x I|} + |∂y d̂|·e^{−|∂y I|} with d̂ = d / mean(d) per image (scalar)."""
    disp = disparity.unsqueeze(1)
    disp = disp / (disp.mean(dim=(2, 3), keepdim=True) + 1e-7)
    grad_dx = (disp[..., :, 1:] - disp[..., :, :-1]).abs()
    grad_dy = (disp[..., 1:, :] - disp[..., :-1, :]).abs()
    image_dx = (image[..., :, 1:] - image[..., :, :-1]).abs().mean(1, keepdim=True)
    image_dy = (image[..., 1:, :] - image[..., :-1, :]).abs().mean(1, keepdim=True)
    return (grad_dx * torch.exp(-image_dx)).mean() + (grad_dy * torch.exp(-image_dy)).mean()


def left_right_consistent(
    left_disparity: torch.Tensor, right_disparity: torch.Tensor, abs_threshold: float = 1.0, rel_threshold: float = 0.05
) -> torch.Tensor:
    """`(B,1,H,W)` mask of left pixels whose disparity the right view's (warped to the left) confirms."""
    warped, inside = warp_right_to_left(right_disparity.unsqueeze(1), left_disparity)
    tolerance = torch.clamp(rel_threshold * left_disparity.unsqueeze(1), min=abs_threshold)
    return inside & ((left_disparity.unsqueeze(1) - warped).abs() <= tolerance)


@torch.no_grad()
def predict_right_disparity(model: nn.Module, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """Right-view disparity `(B,H,W)` from the mirrored pair (flip both, swap), in eval mode, no gradient."""
    was_training = model.training
    model.eval()
    try:
        mirrored = model(right.flip(-1), left.flip(-1))
    finally:
        model.train(was_training)
    if isinstance(mirrored, (list, tuple)):
        mirrored = mirrored[-1]
    return mirrored.flip(-1)


def self_supervised_loss(
    predictions: list[torch.Tensor],
    left: torch.Tensor,
    right: torch.Tensor,
    weights: tuple[float, ...],
    config: SelfSupConfig = SelfSupConfig(),
    right_disparity: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Weighted photometric + smoothness loss of the `(B,H,W)` predictions for RGB [0,1] `(B,3,H,W)` images.

    `right_disparity` `(B,H,W)`, when given, masks left–right inconsistent pixels (occlusions).
    Returns the loss and {"photometric", "smoothness", "masked_fraction"} of the last head.
    """
    total = left.new_zeros(())
    stats: dict[str, float] = {}
    for weight, pred in zip(weights, predictions):
        pred = pred.float()
        warped, mask = warp_right_to_left(right, pred)
        if right_disparity is not None:
            mask = mask & left_right_consistent(
                pred.detach(), right_disparity, config.lr_abs_threshold, config.lr_rel_threshold
            )
        mask = mask.float()
        photometric = (photometric_error(left, warped, config.ssim_weight) * mask).sum() / mask.sum().clamp(min=1.0)
        smoothness = edge_aware_smoothness(pred, left)
        total = total + weight * (photometric + config.smoothness_weight * smoothness)
        stats = {
            "photometric": float(photometric.detach()),
            "smoothness": float(smoothness.detach()),
            "masked_fraction": float(1.0 - mask.mean()),
        }
    return total, stats


class SelfSupervisedTrainer(Trainer):
    """The Trainer with the self-supervised loss in place of the supervised one (ground truth unused)."""

    def __init__(self, *args: Any, selfsup: SelfSupConfig = SelfSupConfig(), **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.selfsup = selfsup

    def compute_loss(self, batch: dict[str, Any]) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Forward of one micro-batch and its self-supervised loss (right disparity first, for the LR check)."""
        left, right = batch["left"], batch["right"]
        right_disparity = None
        if self.selfsup.lr_check:
            right_disparity = predict_right_disparity(self.model, left, right)
            keep_frozen_in_eval(self.model, self.frozen)
        with autocast_context(self.device, self.config.train.precision):
            predictions = self.net(left, right)
        loss, _ = self_supervised_loss(
            predictions,
            denormalize(left),
            denormalize(right),
            tuple(self.config.train.loss_weights),
            self.selfsup,
            right_disparity,
        )
        return loss, predictions
