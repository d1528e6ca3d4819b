"""Concatenation cost volume, built without a loop over disparities and written once."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def concat_cost_volume(
    left: torch.Tensor,
    right: torch.Tensor,
    disparities: int,
    memory_format: torch.memory_format = torch.contiguous_format,
) -> torch.Tensor:
    """Stack left features with right features shifted by d = 0..disparities-1.

    left, right: (B, C, h, w) features at ¼ resolution; returns (B, 2C, disparities, h, w) in
    `memory_format` (`torch.channels_last_3d` is what oneDNN's 3D convolutions run fastest on).
    Slice d holds left[x] and right[x − d]; columns x < d are zero in both halves (PSMNet).
    The volume is allocated once and both halves are written straight into it by one broadcast
    multiply and one gather: no intermediate copy of the volume (its largest tensor) exists.
    """
    b, c, h, w = left.shape
    # source[d, x]: the column of `right` that slice d shows at column x (negative: none).
    source = torch.arange(w, device=left.device)[None, :] - torch.arange(disparities, device=left.device)[:, None]
    visible = (source >= 0).to(left.dtype)[None, None, :, None, :]
    # A zero column in front of `right`: every column with no source gathers it.
    padded = F.pad(right, (1, 0)).unsqueeze(2).expand(b, c, disparities, h, w + 1)
    index = (source + 1).clamp(min=0).view(1, 1, disparities, 1, w).expand(b, c, disparities, h, w)
    needs_graph = torch.is_grad_enabled() and (left.requires_grad or right.requires_grad)
    if needs_graph or torch.onnx.is_in_onnx_export():  # autograd and the exporter record no `out=` writes
        return torch.cat([left.unsqueeze(2) * visible, torch.gather(padded, 4, index)], dim=1)
    volume = torch.empty(
        (b, 2 * c, disparities, h, w), dtype=left.dtype, device=left.device, memory_format=memory_format
    )
    torch.mul(left.unsqueeze(2), visible, out=volume[:, :c])
    torch.gather(padded, 4, index, out=volume[:, c:])
    return volume
