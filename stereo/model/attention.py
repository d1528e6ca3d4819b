"""EMCStereo's three attention modules: EMA, MSFblock and CoordAtt (paper, Sec. 3.1).

Parameter counts pinned by the paper: EMA(128, 16 groups) 672, MSFBlock(32) 5,184,
CoordAtt(32, reduction 8) 856.
"""

from __future__ import annotations

import torch
from torch import nn


class EMA(nn.Module):
    """Efficient Multi-scale Attention (Ouyang et al. 2023) over channel groups.

    Per group of C/g channels: a coordinate branch (height and width pooling through a shared
    1×1 conv, sigmoid gates) and a parallel 3×3 branch; the two are coupled by a cross-spatial
    softmax attention and the result re-weights the input. Shapes are kept: (B, C, H, W).
    """

    def __init__(self, channels: int, groups: int = 16) -> None:
        super().__init__()
        if channels % groups:
            raise ValueError(f"EMA: channels {channels} must be divisible by groups {groups}")
        self.groups = groups
        group_ch = channels // groups
        self.gn = nn.GroupNorm(group_ch, group_ch)
        self.conv1x1 = nn.Conv2d(group_ch, group_ch, kernel_size=1)
        self.conv3x3 = nn.Conv2d(group_ch, group_ch, kernel_size=3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        g = x.reshape(b * self.groups, c // self.groups, h, w)
        pooled_h = g.mean(dim=3, keepdim=True)  # (BG, c, H, 1)
        pooled_w = g.mean(dim=2, keepdim=True).permute(0, 1, 3, 2)  # (BG, c, W, 1)
        gates = self.conv1x1(torch.cat([pooled_h, pooled_w], dim=2))
        gate_h, gate_w = torch.split(gates, [h, w], dim=2)
        coord = self.gn(g * gate_h.sigmoid() * gate_w.permute(0, 1, 3, 2).sigmoid())
        local = self.conv3x3(g)
        coord_desc = torch.softmax(coord.mean(dim=(2, 3)), dim=-1).unsqueeze(1)  # (BG, 1, c)
        local_desc = torch.softmax(local.mean(dim=(2, 3)), dim=-1).unsqueeze(1)
        coord_flat = coord.reshape(b * self.groups, c // self.groups, h * w)
        local_flat = local.reshape(b * self.groups, c // self.groups, h * w)
        weights = torch.bmm(coord_desc, local_flat) + torch.bmm(local_desc, coord_flat)  # (BG, 1, HW)
        out = g * weights.reshape(b * self.groups, 1, h, w).sigmoid()
        return out.reshape(b, c, h, w)


class _ChannelDescriptor(nn.Module):
    """Global average pool + bias-free 1×1 conv: one channel descriptor per pyramid branch."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, kernel_size=1, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x.mean(dim=(2, 3), keepdim=True))


class MSFBlock(nn.Module):
    """Multi-scale fusion (SHISRCNet): learned softmax weights over four pyramid branches.

    `f = proj(Σ_i w_i ⊙ b_i)` with `w = softmax_i(sigmoid(desc_i))`, channel-wise. Input: four
    (B, C, H, W) tensors in the order (b4, b3, b2, b1); output (B, C, H, W).
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.project = nn.Sequential(
            nn.Conv2d(channels, channels, kernel_size=1, bias=False),
            nn.BatchNorm2d(channels),
            nn.ReLU(inplace=True),
        )
        self.se1 = _ChannelDescriptor(channels)
        self.se2 = _ChannelDescriptor(channels)
        self.se3 = _ChannelDescriptor(channels)
        self.se4 = _ChannelDescriptor(channels)

    def forward(self, branches: list[torch.Tensor]) -> torch.Tensor:
        descriptors = [se(x) for se, x in zip((self.se1, self.se2, self.se3, self.se4), branches)]
        weights = torch.softmax(torch.stack(descriptors, dim=1).sigmoid(), dim=1)  # (B, 4, C, 1, 1)
        fused = (torch.stack(branches, dim=1) * weights).sum(dim=1)
        return self.project(fused)


class HSwish(nn.Module):
    """Hard swish, x·ReLU6(x+3)/6, the activation CoordAtt uses."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.nn.functional.relu6(x + 3.0) / 6.0


class CoordAtt(nn.Module):
    """Coordinate Attention (Hou et al. 2021): `f ← f ⊙ a_h ⊙ a_w`, pooling along H and W apart.

    Hidden width `max(8, in_ch // reduction)`. Input and output (B, C, H, W).
    """

    def __init__(self, in_ch: int, out_ch: int, reduction: int = 8) -> None:
        super().__init__()
        hidden = max(8, in_ch // reduction)
        self.conv1 = nn.Conv2d(in_ch, hidden, kernel_size=1)
        self.bn1 = nn.BatchNorm2d(hidden)
        self.act = HSwish()
        self.conv_h = nn.Conv2d(hidden, out_ch, kernel_size=1)
        self.conv_w = nn.Conv2d(hidden, out_ch, kernel_size=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[2:]
        pooled_h = x.mean(dim=3, keepdim=True)  # (B, C, H, 1)
        pooled_w = x.mean(dim=2, keepdim=True).permute(0, 1, 3, 2)  # (B, C, W, 1)
        y = self.act(self.bn1(self.conv1(torch.cat([pooled_h, pooled_w], dim=2))))
        y_h, y_w = torch.split(y, [h, w], dim=2)
        a_h = self.conv_h(y_h).sigmoid()
        a_w = self.conv_w(y_w.permute(0, 1, 3, 2)).sigmoid()
        return x * a_w * a_h
