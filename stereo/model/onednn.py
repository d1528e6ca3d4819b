"""Convolutions that call oneDNN directly on CPU, with the following ReLU fused in.

PyTorch's CPU dispatch sends a 3D convolution to a slow reference kernel when
`B·C·D·H` ≤ 20,480 (the ¼-size hourglass levels at 384×1248 fall below it) and a transposed 3D
convolution with a bias always; a separate ReLU is one more pass over the activation. The
`mkldnn._convolution_pointwise` operators (what `torch.compile` emits on CPU) have neither
problem. They are private to PyTorch, so every module here falls back to the public functional
call where they are missing or misbehave (`onednn_available` checks them once), on other devices
and for other dtypes; both paths compute the same (tested).
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import nn

_CONVS = (nn.Conv2d, nn.Conv3d)
_TRANSPOSED = (nn.ConvTranspose2d, nn.ConvTranspose3d)
_ONEDNN_DTYPES = (torch.float32, torch.bfloat16)


@functools.cache
def onednn_available() -> bool:
    """Whether this PyTorch build's private oneDNN operators exist and take the arguments used here.

    Checked once by calling both on a tiny input and comparing with the public functional
    convolution: a PyTorch release that drops them or changes their signature or meaning makes
    every module here use the public path instead of failing.
    """
    ops = getattr(torch.ops, "mkldnn", None)
    if not (
        torch.backends.mkldnn.is_available()
        and ops is not None
        and hasattr(ops, "_convolution_pointwise")
        and hasattr(ops, "_convolution_transpose_pointwise")
    ):
        return False
    generator = torch.Generator().manual_seed(0)
    x = torch.randn(1, 2, 4, 4, generator=generator).contiguous(memory_format=torch.channels_last)
    weight = torch.randn(3, 2, 3, 3, generator=generator).contiguous(memory_format=torch.channels_last)
    bias = torch.randn(3, generator=generator)
    try:
        with torch.no_grad():
            fused = ops._convolution_pointwise(x, weight, bias, [1, 1], [1, 1], [1, 1], 1, "relu", [], "")
            transposed = ops._convolution_transpose_pointwise(
                fused, weight, bias[:2], [1, 1], [1, 1], [2, 2], [1, 1], 1, "none", [], ""
            )
            return torch.allclose(fused, F.relu(F.conv2d(x, weight, bias, 1, 1)), atol=1e-5) and torch.allclose(
                transposed, F.conv_transpose2d(fused, weight, bias[:2], 2, 1, 1), atol=1e-5
            )
    except (RuntimeError, TypeError):
        return False


def channels_last(weight: torch.Tensor) -> torch.Tensor:
    """A detached copy of a 4D or 5D weight in the channels-last layout of its rank."""
    layout = torch.channels_last if weight.dim() == 4 else torch.channels_last_3d
    return weight.detach().clone().contiguous(memory_format=layout)


def _runs_on_onednn(x: torch.Tensor, enabled: bool) -> bool:
    return enabled and x.device.type == "cpu" and x.dtype in _ONEDNN_DTYPES


class FusedConv(nn.Module):
    """`conv(x)` optionally followed by ReLU, one oneDNN call on CPU (weights and bias copied)."""

    def __init__(self, conv: nn.Module, relu: bool, use_onednn: bool = True) -> None:
        super().__init__()
        if not isinstance(conv, _CONVS) or isinstance(conv.padding, str):
            raise TypeError(f"FusedConv takes a Conv2d/Conv3d with numeric padding, got {conv!r}")
        self.weight = nn.Parameter(channels_last(conv.weight), requires_grad=False)
        self.bias = None if conv.bias is None else nn.Parameter(conv.bias.detach().clone(), requires_grad=False)
        self.stride, self.padding, self.dilation = list(conv.stride), list(conv.padding), list(conv.dilation)
        self.groups = conv.groups
        self.relu = relu
        self.use_onednn = use_onednn and onednn_available()
        self._functional = F.conv2d if isinstance(conv, nn.Conv2d) else F.conv3d

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if _runs_on_onednn(x, self.use_onednn):
            return torch.ops.mkldnn._convolution_pointwise(
                x,
                self.weight,
                self.bias,
                self.padding,
                self.stride,
                self.dilation,
                self.groups,
                "relu" if self.relu else "none",
                [],
                "",
            )
        y = self._functional(x, self.weight, self.bias, self.stride, self.padding, self.dilation, self.groups)
        return F.relu_(y) if self.relu else y


class FusedConvTranspose(nn.Module):
    """A transposed convolution (with bias) as one oneDNN call on CPU; the functional one elsewhere."""

    def __init__(self, conv: nn.Module, use_onednn: bool = True) -> None:
        super().__init__()
        if not isinstance(conv, _TRANSPOSED) or conv.groups != 1:
            raise TypeError(f"FusedConvTranspose takes an ungrouped ConvTranspose2d/3d, got {conv!r}")
        self.weight = nn.Parameter(conv.weight.detach().clone(), requires_grad=False)
        self.bias = None if conv.bias is None else nn.Parameter(conv.bias.detach().clone(), requires_grad=False)
        self.stride, self.padding = list(conv.stride), list(conv.padding)
        self.output_padding, self.dilation = list(conv.output_padding), list(conv.dilation)
        self.use_onednn = use_onednn and onednn_available()
        self._functional = F.conv_transpose2d if isinstance(conv, nn.ConvTranspose2d) else F.conv_transpose3d

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if _runs_on_onednn(x, self.use_onednn):
            return torch.ops.mkldnn._convolution_transpose_pointwise(
                x,
                self.weight,
                self.bias,
                self.padding,
                self.output_padding,
                self.stride,
                self.dilation,
                1,
                "none",
                [],
                "",
            )
        return self._functional(
            x, self.weight, self.bias, self.stride, self.padding, self.output_padding, 1, self.dilation
        )


class DepthSplitConv3d(nn.Module):
    """A stride-1 3D convolution to few output channels as one 2D convolution over depth slices.

    oneDNN runs a 3D convolution to a single output channel (the classifiers' last layer) at a
    few GFLOP/s. Here every depth slice is convolved in 2D to `kd·out` channels, one group per
    depth tap, and the taps are summed with their depth shifts: the same sum, about 2× faster.
    Input (B, C, D, H, W), preferably channels-last 3D; output (B, out, D, H, W).
    """

    def __init__(self, conv: nn.Module, use_onednn: bool = True) -> None:
        super().__init__()
        if (
            not isinstance(conv, nn.Conv3d)
            or tuple(conv.stride) != (1, 1, 1)
            or tuple(conv.dilation) != (1, 1, 1)
            or conv.groups != 1
            or isinstance(conv.padding, str)
        ):
            raise TypeError(f"DepthSplitConv3d takes an ungrouped, undilated stride-1 Conv3d, got {conv!r}")
        out_ch, in_ch, taps = conv.weight.shape[:3]
        slices = conv.weight.detach().permute(2, 0, 1, 3, 4).reshape(taps * out_ch, in_ch, *conv.weight.shape[3:])
        self.weight = nn.Parameter(channels_last(slices), requires_grad=False)
        self.bias = None if conv.bias is None else nn.Parameter(conv.bias.detach().clone(), requires_grad=False)
        self.out_channels, self.taps, self.depth_padding = out_ch, taps, conv.padding[0]
        self.padding = list(conv.padding[1:])
        self.use_onednn = use_onednn and onednn_available()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        batch, channels, depth, height, width = x.shape
        planes = x.transpose(1, 2).reshape(batch * depth, channels, height, width)
        if _runs_on_onednn(x, self.use_onednn):
            per_tap = torch.ops.mkldnn._convolution_pointwise(
                planes, self.weight, None, self.padding, [1, 1], [1, 1], 1, "none", [], ""
            )
        else:
            per_tap = F.conv2d(planes, self.weight, None, 1, self.padding)
        per_tap = per_tap.reshape(batch, depth, self.taps, self.out_channels, *per_tap.shape[2:])
        out_depth = depth + 2 * self.depth_padding - self.taps + 1
        out = per_tap.new_zeros((batch, out_depth, self.out_channels, *per_tap.shape[4:]))
        for tap in range(self.taps):
            # Output slice d reads input slice d + tap − padding.
            first = max(0, self.depth_padding - tap)
            last = min(out_depth, depth + self.depth_padding - tap)
            if last > first:
                out[:, first:last] += per_tap[
                    :, first + tap - self.depth_padding : last + tap - self.depth_padding, tap
                ]
        if self.bias is not None:
            out += self.bias.reshape(1, 1, -1, 1, 1)
        return out.transpose(1, 2)


#: Below this many output channels a stride-1 3D convolution runs as a `DepthSplitConv3d`.
DEPTH_SPLIT_MAX_CHANNELS = 4


def fuse_convolutions(module: nn.Module, use_onednn: bool = True) -> nn.Module:
    """Replace, in place, every convolution of an inference-only module by its fused equivalent.

    Inside a Sequential, a convolution followed by a ReLU (with only Identity between, which is
    what `fold_batchnorms` leaves) takes the ReLU in and the ReLU becomes Identity; a stride-1 3D
    convolution to fewer than `DEPTH_SPLIT_MAX_CHANNELS` channels becomes a `DepthSplitConv3d`.
    Returns `module`.
    """
    for parent in list(module.modules()):
        children = list(parent.named_children())
        for index, (name, child) in enumerate(children):
            if isinstance(child, _TRANSPOSED):
                setattr(parent, name, FusedConvTranspose(child, use_onednn))
            elif (
                isinstance(child, nn.Conv3d)
                and child.out_channels < DEPTH_SPLIT_MAX_CHANNELS
                and tuple(child.stride) == (1, 1, 1)
                and tuple(child.dilation) == (1, 1, 1)
                and child.groups == 1
                and _following_relu(parent, children, index) is None
            ):
                setattr(parent, name, DepthSplitConv3d(child, use_onednn))
            elif isinstance(child, _CONVS):
                relu_name = _following_relu(parent, children, index)
                setattr(parent, name, FusedConv(child, relu=relu_name is not None, use_onednn=use_onednn))
                if relu_name is not None:
                    setattr(parent, relu_name, nn.Identity())
    return module


def _following_relu(parent: nn.Module, children: list[tuple[str, nn.Module]], index: int) -> str | None:
    """Name of the ReLU after children[index] in a Sequential, skipping Identity; None if there is none."""
    if not isinstance(parent, nn.Sequential):
        return None
    for name, child in children[index + 1 :]:
        if isinstance(child, nn.ReLU):
            return name
        if not isinstance(child, nn.Identity):
            return None
    return None
