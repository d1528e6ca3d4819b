"""Concatenation cost volume, written once into a single preallocated tensor."""
from __future__ import annotations

import torch


def concat_cost_volume(left: torch.Tensor, right: torch.Tensor, disparities: int,
                       memory_format: torch.memory_format = torch.contiguous_format) -> torch.Tensor:
    """Stack left features with right features shifted by d = 0..disparities-1.

    left, right: (B, C, h, w) features at ¼ resolution; returns (B, 2C, disparities, h, w) in
    `memory_format` (`torch.channels_last_3d` is what oneDNN's 3D convolutions run fastest on).
    Slice d holds left[x] and right[x − d]; columns x < d are zero in both halves (PSMNet).
    The volume is allocated once and each slice is copied straight into it: no intermediate
    shifted or masked copy of the whole volume exists (it is the largest tensor of the network).
    """
    b, c, h, w = left.shape
    volume = torch.empty((b, 2 * c, disparities, h, w), dtype=left.dtype, device=left.device,
                         memory_format=memory_format)
    for d in range(disparities):
        if d:  # no empty slice assignment: ONNX export cannot express it
            volume[:, :, d, :, :d] = 0
        volume[:, :c, d, :, d:] = left[..., d:]
        volume[:, c:, d, :, d:] = right[..., : w - d]
    return volume
