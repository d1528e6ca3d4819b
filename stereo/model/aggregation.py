"""Stacked-hourglass 3D cost aggregation (PSMNet) with three residually refined heads."""

from __future__ import annotations

from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch import nn

from .layers import conv_bn, conv_bn_relu


def _deconv_bn(in_ch: int, out_ch: int) -> nn.Sequential:
    return nn.Sequential(
        nn.ConvTranspose3d(in_ch, out_ch, 3, stride=2, padding=1, output_padding=1, bias=False),
        nn.BatchNorm3d(out_ch),
    )


class Hourglass(nn.Module):
    """3D encoder–decoder; `forward(x, presqu, postsqu) -> (out, pre, post)` as in PSMNet."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        wide = channels * 2
        self.conv1 = conv_bn_relu(channels, wide, 3, 2, 1, dims=3)
        self.conv2 = conv_bn(wide, wide, 3, 1, 1, dims=3)
        self.conv3 = conv_bn_relu(wide, wide, 3, 2, 1, dims=3)
        self.conv4 = conv_bn_relu(wide, wide, 3, 1, 1, dims=3)
        self.conv5 = _deconv_bn(wide, wide)
        self.conv6 = _deconv_bn(wide, channels)

    def forward(
        self, x: torch.Tensor, presqu: torch.Tensor | None, postsqu: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        pre = self.conv2(self.conv1(x))
        pre = F.relu(pre + postsqu if postsqu is not None else pre, inplace=True)
        out = self.conv4(self.conv3(pre))
        post = F.relu(self.conv5(out) + (presqu if presqu is not None else pre), inplace=True)
        return self.conv6(post), pre, post


def _classifier() -> nn.Sequential:
    return nn.Sequential(conv_bn_relu(32, 32, 3, 1, 1, dims=3), nn.Conv3d(32, 1, 3, padding=1, bias=False))


class StackedHourglass(nn.Module):
    """Regularises a (B, 64, D/4, h, w) volume into 1-channel costs (B, 1, D/4, h, w).

    `forward(volume)` returns the three costs c1, c2 += c1, c3 += c2; at inference only the
    third is needed, but it depends on all three hourglasses and on c1 and c2. `wiring` chooses
    the third hourglass's skip input (see `ModelConfig.hourglass_wiring`).
    """

    def __init__(self, wiring: str = "openstereo") -> None:
        super().__init__()
        if wiring not in ("psmnet", "openstereo"):
            raise ValueError(f"hourglass wiring must be 'psmnet' or 'openstereo', got {wiring!r}")
        #: "psmnet": the third hourglass takes `pre1` as its skip (PSMNet's code); "openstereo":
        #: it takes `pre2`, the second hourglass's own (OpenStereo's PSMNet, the authors' base).
        self.wiring = wiring
        self.dres0 = nn.Sequential(conv_bn_relu(64, 32, 3, 1, 1, dims=3), conv_bn_relu(32, 32, 3, 1, 1, dims=3))
        self.dres1 = nn.Sequential(conv_bn_relu(32, 32, 3, 1, 1, dims=3), conv_bn(32, 32, 3, 1, 1, dims=3))
        self.dres2 = Hourglass(32)
        self.dres3 = Hourglass(32)
        self.dres4 = Hourglass(32)
        self.classif1 = _classifier()
        self.classif2 = _classifier()
        self.classif3 = _classifier()

    def forward(self, volume: torch.Tensor) -> list[torch.Tensor]:
        return list(self.costs(volume))

    def costs(self, volume: torch.Tensor) -> Iterator[torch.Tensor]:
        """Yield c1, c2 = c1 + ·, c3 = c2 + · in turn, each (B, 1, D/4, h, w).

        Each hourglass output is dropped as soon as its head and the next hourglass have used
        it, so a consumer that keeps only the last cost (inference) holds at most two 32-channel
        volumes besides `cost0` at any time.
        """
        for layer in self.dres0:  # layer by layer, so the 64-channel volume is freed after the first
            volume = layer(volume)
        cost0 = self.dres1(volume) + volume
        del volume
        out, pre1, post = self.dres2(cost0, None, None)
        out = out + cost0
        cost = self.classif1(out)
        yield cost
        out, pre2, post = self.dres3(out, pre1, post)
        skip = pre1 if self.wiring == "psmnet" else pre2
        del pre1, pre2
        out = out + cost0
        cost = self.classif2(out) + cost
        yield cost
        out, _, _ = self.dres4(out, skip, post)
        out = out + cost0
        del cost0, skip, post
        yield self.classif3(out) + cost
