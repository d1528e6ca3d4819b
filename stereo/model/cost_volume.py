"""Concatenation cost volume, built in one vectorised operation (no loop over disparities)."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def concat_cost_volume(left: torch.Tensor, right: torch.Tensor, disparities: int) -> torch.Tensor:
    """Stack left features with right features shifted by d = 0..disparities-1.

    left, right: (B, C, h, w) features at ¼ resolution; returns (B, 2C, disparities, h, w).
    Slice d holds left[x] and right[x − d]; columns x < d are zero in both halves (PSMNet).
    """
    b, c, h, w = left.shape
    # Right features padded with d_max − 1 zero columns on the left; window d starts at
    # column (d_max − 1 − d), so each window is `right` shifted right by d with zeros in front.
    padded = F.pad(right, (disparities - 1, 0))
    windows = padded.unfold(3, w, 1).flip(3)            # (B, C, h, D, w)
    shifted = windows.permute(0, 1, 3, 2, 4)             # (B, C, D, h, w)
    columns = torch.arange(w, device=left.device)
    shifts = torch.arange(disparities, device=left.device)
    valid = (columns[None, :] >= shifts[:, None]).to(left.dtype)  # (D, w)
    left_part = left.unsqueeze(2) * valid[None, None, :, None, :]
    return torch.cat([left_part, shifted], dim=1).contiguous()
