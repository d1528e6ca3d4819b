"""Feature stage: PSMNet's residual stem and SPP with EMCStereo's three attention modules inside.

Input (B, 3, H, W) ImageNet-normalised, H and W multiples of 32 and ≥ 256 (the 64×64 pool of
`branch1` runs on the ¼-resolution feature); output the 32-channel matching feature
(B, 32, H/4, W/4).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .attention import EMA, CoordAtt, MSFBlock
from .layers import conv_bn, conv_bn_relu

#: Average-pool sizes of the four SPP branches, branch1..branch4.
SPP_POOLS = (64, 32, 16, 8)


class BasicBlock(nn.Module):
    """Residual block: conv-BN-ReLU, conv-BN, plus the shortcut; no ReLU after the sum (PSMNet)."""

    def __init__(self, in_ch: int, out_ch: int, stride: int, dilation: int) -> None:
        super().__init__()
        self.conv1 = conv_bn_relu(in_ch, out_ch, 3, stride, 1, dilation)
        self.conv2 = conv_bn(out_ch, out_ch, 3, 1, 1, dilation)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_ch != out_ch:
            # The authors' 1×1 shortcut conv carries a bias (PSMNet's does not).
            self.downsample = conv_bn(in_ch, out_ch, 1, stride, 0, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shortcut = x if self.downsample is None else self.downsample(x)
        return self.conv2(self.conv1(x)) + shortcut


def _residual_stage(in_ch: int, out_ch: int, blocks: int, stride: int, dilation: int) -> nn.Sequential:
    layers = [BasicBlock(in_ch, out_ch, stride, dilation)]
    layers += [BasicBlock(out_ch, out_ch, 1, dilation) for _ in range(blocks - 1)]
    return nn.Sequential(*layers)


def _spp_branch(pool: int) -> nn.Sequential:
    return nn.Sequential(nn.AvgPool2d(pool, stride=pool), conv_bn_relu(128, 32, 1, 1, 0))


class FeatureBackbone(nn.Module):
    """Shared-weight feature extractor; `ema`, `msf` and `coord` switch the attention modules."""

    def __init__(self, ema: bool = True, msf: bool = True, coord: bool = True) -> None:
        super().__init__()
        self.firstconv = nn.Sequential(
            conv_bn_relu(3, 32, 3, 2, 1), conv_bn_relu(32, 32, 3, 1, 1), conv_bn_relu(32, 32, 3, 1, 1)
        )
        self.layer1 = _residual_stage(32, 32, 3, 1, 1)
        self.layer2 = _residual_stage(32, 64, 16, 2, 1)
        self.layer3 = _residual_stage(64, 128, 3, 1, 1)
        self.layer4 = _residual_stage(128, 128, 3, 1, 2)
        self.ema = EMA(128, groups=16) if ema else None
        self.branch1, self.branch2, self.branch3, self.branch4 = (_spp_branch(p) for p in SPP_POOLS)
        self.msf = MSFBlock(32) if msf else None
        pyramid_ch = 32 if msf else 4 * 32
        self.lastconv = nn.Sequential(
            conv_bn_relu(64 + 128 + pyramid_ch, 128, 3, 1, 1),
            nn.Conv2d(128, 32, kernel_size=1, bias=False),
        )
        self.coord_att = CoordAtt(32, 32, reduction=8) if coord else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out_4 = self.layer2(self.layer1(self.firstconv(x)))
        out_8 = self.layer4(self.layer3(out_4))
        if self.ema is not None:
            out_8 = self.ema(out_8)
        size = out_8.shape[2:]
        pyramid = [
            F.interpolate(branch(out_8), size=size, mode="bilinear", align_corners=True)
            for branch in (self.branch4, self.branch3, self.branch2, self.branch1)
        ]
        fused = [self.msf(pyramid)] if self.msf is not None else pyramid
        feature = self.lastconv(torch.cat([out_4, out_8, *fused], dim=1))
        if self.coord_att is not None:
            feature = self.coord_att(feature)
        return feature
