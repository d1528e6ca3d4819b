"""From a low-resolution cost to a full-resolution disparity: trilinear upsampling + soft-argmin."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def upsample_cost(
    cost: torch.Tensor, disparities: int, height: int, width: int, max_disp: int, align_corners: bool = True
) -> torch.Tensor:
    """Trilinear upsampling of (B, 1, Dl, h, w) to (B, disparities, H, W), as the model was trained.

    With `disparities == max_disp` this is exactly `interpolate(…, [D, H, W], mode='trilinear',
    align_corners=align_corners)`: `True` is the authors' (OpenStereo) call, `False` what PSMNet's
    call does on PyTorch ≥ 0.4.1. A shorter range (range-limited inference) keeps the full range's
    disparity scale (`depth_positions`), so output index d still means d pixels.
    """
    deep = upsample_depth(cost, disparities, max_disp, align_corners)
    return F.interpolate(deep, size=(height, width), mode="bilinear", align_corners=align_corners)


def depth_positions(
    disparities: int, max_disp: int, align_corners: bool, device: torch.device | None = None
) -> torch.Tensor:
    """Where output disparity d = 0…disparities−1 samples the ¼-resolution depth axis (float64 slices).

    The scale is the full range's (`max_disp` → `max_disp // 4` slices), as `F.interpolate` maps
    it: `d · (Dl − 1)/(D − 1)` with `align_corners`, else `(d + ½) · Dl/D − ½` clamped at 0.
    """
    index = torch.arange(disparities, device=device, dtype=torch.float64)
    low = max_disp // 4
    if align_corners:
        return index * ((low - 1) / (max_disp - 1))
    return ((index + 0.5) * (low / max_disp) - 0.5).clamp(min=0.0)


def upsample_depth(cost: torch.Tensor, disparities: int, max_disp: int, align_corners: bool) -> torch.Tensor:
    """Linear interpolation along depth only: (B, 1, Dl, h, w) → (B, disparities, h, w).

    Index d samples the low-resolution slice at `depth_positions(…)[d]`, clamped to the slices present.
    """
    low = cost[:, 0]  # (B, Dl, h, w)
    lower, upper, frac = _linear_taps(depth_positions(disparities, max_disp, align_corners, cost.device), low.shape[1])
    frac = frac.to(low.dtype)[None, :, None, None]
    return low[:, lower] * (1 - frac) + low[:, upper] * frac  # (B, D, h, w)


def _linear_taps(pos: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Neighbour indices and weight of the upper one for sampling positions `pos` on 0..size-1."""
    pos = pos.clamp(0, size - 1)
    lower = pos.floor().long().clamp(max=size - 1)
    upper = (lower + 1).clamp(max=size - 1)
    return lower, upper, pos - lower


def _resize_taps(
    out_size: int, in_size: int, align_corners: bool, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`_linear_taps` of bilinear resizing from `in_size` to `out_size` samples.

    Positions are computed in float32 as PyTorch's own `interpolate` does, so both round alike.
    """
    index = torch.arange(out_size, device=device, dtype=torch.float32)
    if align_corners:
        scale = (in_size - 1) / (out_size - 1) if out_size > 1 else 0.0
        return _linear_taps(index * torch.tensor(scale, dtype=torch.float32, device=device), in_size)
    scale = torch.tensor(in_size / out_size, dtype=torch.float32, device=device)
    return _linear_taps(((index + 0.5) * scale - 0.5).clamp(min=0.0), in_size)


def upsampled_soft_argmin(
    cost: torch.Tensor,
    values: torch.Tensor,
    height: int,
    width: int,
    max_disp: int,
    align_corners: bool = True,
    radius: float = 2.0,
    rows_per_chunk: int = 32,
) -> tuple[torch.Tensor, torch.Tensor]:
    """`DisparityRegression.with_confidence(upsample_cost(…))` without the full-resolution volume.

    cost (B, 1, Dl, h, w) low-resolution costs; values (D,) the disparity of each upsampled
    index, which must be 0, 1, …, D−1 (the confidence window is found by index). Returns
    disparity and confidence (B, height, width), float32. Softmax is per pixel, so output rows
    can be produced `rows_per_chunk` at a time, exactly: only a (B, D, rows_per_chunk, width)
    block ever exists (the full volume is D·H·W floats, 368 MB at 384×1248 and 1.6 GB at
    1088×1920). Rows are interpolated here at low width; the width is left to `F.interpolate`
    (full width, so the same weights as the reference path).
    """
    if rows_per_chunk <= 0:
        raise ValueError(f"rows_per_chunk must be positive, got {rows_per_chunk}")
    values = values.float()
    depth = values.numel()
    deep = upsample_depth(cost.float(), depth, max_disp, align_corners)  # (B, D, h, w)
    batch = deep.shape[0]
    row_lo, row_hi, row_frac = _resize_taps(height, deep.shape[2], align_corners, cost.device)
    window = torch.arange(int(2 * radius) + 1, device=cost.device)
    disparity, confidence = [], []
    for top in range(0, height, rows_per_chunk):
        rows = slice(top, min(top + rows_per_chunk, height))
        count = rows.stop - rows.start
        low_rows = torch.lerp(
            deep[:, :, row_lo[rows]],
            deep[:, :, row_hi[rows]],
            row_frac[rows][None, None, :, None].expand(batch, depth, -1, deep.shape[3]),
        )
        prob = torch.softmax(
            F.interpolate(low_rows, size=(count, width), mode="bilinear", align_corners=align_corners), dim=1
        )
        estimate = torch.matmul(values, prob.reshape(batch, depth, count * width)).reshape(batch, count, width)
        disparity.append(estimate)
        # Confidence: the probability within ±radius of the estimate, i.e. of the integer
        # disparities ceil(d̂ − r) … floor(d̂ + r), at most 2r + 1 of them.
        candidates = torch.ceil(estimate - radius).clamp(min=0).long().unsqueeze(1) + window[:, None, None]
        index = candidates.clamp(max=depth - 1)
        near = (candidates < depth) & ((values[index] - estimate.unsqueeze(1)).abs() <= radius)
        confidence.append((prob.gather(1, index) * near).sum(dim=1).clamp_(0.0, 1.0))
    return torch.cat(disparity, dim=1), torch.cat(confidence, dim=1)


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
