"""`BranchNet`: a small U-Net that labels each pixel background, trunk or branch from image + disparity.

Input: 5 channels at the frame's size — RGB, disparity divided by its 95th percentile (so the
network sees the scene's relative depth whatever the camera's focal length and baseline), and
the disparity's validity. The encoder starts at half resolution (strided stem) and goes to 1/16,
where a dilated convolution gives the context that tells a trunk from a branch; a light head at
full resolution sees the input again, so branches 1–2 px wide keep their pixels. With `fine_width` > 0
the head sees, instead of the raw input, `fine_width` features of two full-resolution convolutions of
it: a stem 2 px wide is one pixel at the encoder's first scale, and the raw pixels alone left the head
too little to tell a thin stem from the bark or leaves behind it.
With `deep_blocks` > 0 each of the encoder's coarse scales (1/4, 1/8, 1/16) adds that many inverted residual
blocks (`InvertedResidual`, MobileNetV2's): depth and receptive field where a pixel is cheap (1/16 of the frame's
pixels at 1/4, 1/256 at 1/16), to learn a domain as broad as the randomized one (`stereo.synth.randomized`)
without touching the full-resolution head; 0 is the shipped network, layer for layer.
Output: logits `(B, 3, H, W)` for `CLASSES`; H and W must be multiples of `STRIDE` (pad first). The input and its
constants are `branchrange.core.segmentation.network_input`, which the onboard loop uses without torch.

Why this size: about 0.2 M parameters (under 1 MB of float32 weights) and one forward pass at
640×360 within the segmenter's time budget on two CPU cores, trainable on CPU in an hour.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from branchrange.core.segmentation.network_input import CLASSES, IN_CHANNELS


def _conv(c_in: int, c_out: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    """3×3 convolution, batch norm, ReLU."""
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class InvertedResidual(nn.Module):
    """MobileNetV2's inverted residual block at one scale: a 1×1 expansion to `expand` × `channels`, a 3×3
    depthwise convolution (`dilation`), a 1×1 projection back, added to the input. Each convolution is the first
    layer of its own `nn.Sequential` with its batch norm next, as `_conv`'s are (what
    `branchrange.learning.from_onnx` reads a folded ONNX file back by)."""

    def __init__(self, channels: int, expand: int = 4, dilation: int = 1) -> None:
        super().__init__()
        hidden = channels * expand
        self.expand = nn.Sequential(nn.Conv2d(channels, hidden, 1, bias=False), nn.BatchNorm2d(hidden), nn.ReLU())
        self.depthwise = nn.Sequential(
            nn.Conv2d(hidden, hidden, 3, padding=dilation, dilation=dilation, groups=hidden, bias=False),
            nn.BatchNorm2d(hidden),
            nn.ReLU(),
        )
        projection_norm = nn.BatchNorm2d(channels)
        self.project = nn.Sequential(nn.Conv2d(hidden, channels, 1, bias=False), projection_norm)
        # The block starts as the identity (its last batch norm scales by zero): blocks added to a trained network
        # leave its output as it was until training moves them (Goyal et al. 2017's zero-γ residual start).
        nn.init.zeros_(projection_norm.weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """`(B, channels, h, w)` → the same shape."""
        result: torch.Tensor = x + self.project(self.depthwise(self.expand(x)))
        return result


def _deep(channels: int, blocks: int, dilation: int = 1) -> nn.Sequential:
    """`blocks` inverted residual blocks at one scale (none: an empty `nn.Sequential`, the identity, no weights)."""
    return nn.Sequential(*(InvertedResidual(channels, dilation=dilation) for _ in range(blocks)))


class BranchNet(nn.Module):
    """Per-pixel background / trunk / branch logits (see the module docstring); `width` scales the channels,
    `fine_width` (0: none) is the full-resolution feature branch's, `deep_blocks` the inverted residual blocks at
    each of 1/4, 1/8 and 1/16 (0: none, the shipped network)."""

    def __init__(self, width: int = 16, fine_width: int = 0, deep_blocks: int = 0) -> None:
        super().__init__()
        w = width
        self.width, self.fine_width, self.deep_blocks = width, fine_width, deep_blocks
        self.stem = nn.Sequential(_conv(IN_CHANNELS, w, 2), _conv(w, w))  # 1/2
        self.down2 = nn.Sequential(_conv(w, 2 * w, 2), _conv(2 * w, 2 * w), *_deep(2 * w, deep_blocks))  # 1/4
        self.down3 = nn.Sequential(_conv(2 * w, 3 * w, 2), _conv(3 * w, 3 * w), *_deep(3 * w, deep_blocks))  # 1/8
        self.down4 = nn.Sequential(  # 1/16
            _conv(3 * w, 4 * w, 2), _conv(4 * w, 4 * w, dilation=2), *_deep(4 * w, deep_blocks, dilation=2)
        )
        self.up3 = _conv(7 * w, 3 * w)
        self.up2 = _conv(5 * w, 2 * w)
        self.up1 = _conv(3 * w, w)
        self.fine = nn.Sequential(_conv(IN_CHANNELS, fine_width), _conv(fine_width, fine_width)) if fine_width else None
        self.head = nn.Sequential(_conv(w + (fine_width or IN_CHANNELS), w // 2), nn.Conv2d(w // 2, len(CLASSES), 1))

    @staticmethod
    def _up_cat(coarse: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        """`coarse` upsampled ×2 to `skip`'s size, concatenated with it on the channel axis."""
        return torch.cat([F.interpolate(coarse, size=skip.shape[-2:], mode="bilinear", align_corners=False), skip], 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Logits `(B, 3, H, W)` of an input `(B, 5, H, W)` with H, W multiples of `STRIDE`."""
        f1 = self.stem(x)
        f2 = self.down2(f1)
        f3 = self.down3(f2)
        f4 = self.down4(f3)
        d3 = self.up3(self._up_cat(f4, f3))
        d2 = self.up2(self._up_cat(d3, f2))
        d1 = self.up1(self._up_cat(d2, f1))
        full_resolution = x if self.fine is None else self.fine(x)
        logits: torch.Tensor = self.head(self._up_cat(d1, full_resolution))
        return logits
