"""Convolution + BatchNorm building blocks shared by the 2D backbone and the 3D aggregation.

The Sequential layouts (conv at index 0, BN at 1, ReLU at 2) are what give the state_dict its
`…0.weight` / `…1.weight` names, the ones the authors' checkpoint uses.
"""

from __future__ import annotations

from torch import nn


def conv_bn(
    in_ch: int, out_ch: int, kernel: int, stride: int, pad: int, dilation: int = 1, *, dims: int = 2, bias: bool = False
) -> nn.Sequential:
    """Conv (2D or 3D) followed by BatchNorm; padding grows with dilation as in PSMNet."""
    conv_cls = nn.Conv2d if dims == 2 else nn.Conv3d
    bn_cls = nn.BatchNorm2d if dims == 2 else nn.BatchNorm3d
    padding = dilation if dilation > 1 else pad
    return nn.Sequential(
        conv_cls(in_ch, out_ch, kernel, stride=stride, padding=padding, dilation=dilation, bias=bias),
        bn_cls(out_ch),
    )


def conv_bn_relu(
    in_ch: int, out_ch: int, kernel: int, stride: int, pad: int, dilation: int = 1, *, dims: int = 2
) -> nn.Sequential:
    """Conv + BatchNorm + ReLU in one Sequential (keys `.0` conv, `.1` BN)."""
    block = conv_bn(in_ch, out_ch, kernel, stride, pad, dilation, dims=dims)
    block.append(nn.ReLU(inplace=True))
    return block
