"""From a low-resolution cost to a full-resolution disparity: trilinear upsampling + soft-argmin."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def upsample_cost(cost: torch.Tensor, disparities: int, height: int, width: int,
                  depth_step: float) -> torch.Tensor:
    """Trilinear (align_corners) upsampling of (B, 1, Dl, h, w) to (B, disparities, H, W).

    Output disparity index d samples the low-resolution slice at `d · depth_step`, clamped to the
    slices present. With `depth_step = (Dl_full − 1)/(D_full − 1)` this is exactly PSMNet's
    `interpolate(…, [D, H, W], mode='trilinear', align_corners=True)` for the full range, and a
    shorter range (range-limited inference) keeps the same disparity scale the model was trained with.
    """
    low = cost[:, 0]                                        # (B, Dl, h, w)
    slices = low.shape[1]
    pos = torch.arange(disparities, device=cost.device, dtype=torch.float64) * depth_step
    pos = pos.clamp(max=slices - 1)
    lower = pos.floor().long().clamp(max=slices - 1)
    upper = (lower + 1).clamp(max=slices - 1)
    frac = (pos - lower).to(low.dtype)[None, :, None, None]
    along_depth = low[:, lower] * (1 - frac) + low[:, upper] * frac   # (B, D, h, w)
    return F.interpolate(along_depth, size=(height, width), mode="bilinear", align_corners=True)


class DisparityRegression(nn.Module):
    """Soft-argmin, `d̂ = Σ_d d · softmax(c)_d`, with the disparities 0..D−1 as a frozen parameter.

    The frozen `weight` (1, 1, D, 1, 1) is part of the authors' state_dict and parameter count.
    """

    def __init__(self, max_disp: int) -> None:
        super().__init__()
        values = torch.arange(max_disp, dtype=torch.float32).reshape(1, 1, max_disp, 1, 1)
        self.weight = nn.Parameter(values, requires_grad=False)

    def forward(self, cost: torch.Tensor) -> torch.Tensor:
        """cost (B, D', H, W) with D' ≤ D → disparity (B, H, W) in pixels."""
        prob = torch.softmax(cost, dim=1)
        return torch.einsum("bdhw,d->bhw", prob, self._values(cost.shape[1], prob.dtype))

    def with_confidence(self, cost: torch.Tensor, radius: float = 2.0) -> tuple[torch.Tensor, torch.Tensor]:
        """Disparity (B, H, W) and the probability mass within ±`radius` px of it, in [0, 1]."""
        prob = torch.softmax(cost, dim=1)
        values = self._values(cost.shape[1], prob.dtype)
        disparity = torch.einsum("bdhw,d->bhw", prob, values)
        near = (values[None, :, None, None] - disparity[:, None]).abs() <= radius
        confidence = (prob * near).sum(dim=1).clamp(0.0, 1.0)
        return disparity, confidence

    def _values(self, count: int, dtype: torch.dtype) -> torch.Tensor:
        return self.weight.reshape(-1)[:count].to(dtype)
