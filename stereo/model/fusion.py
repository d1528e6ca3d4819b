"""BatchNorm folded into the convolution before it, for an inference-only copy of a module.

In eval mode a BatchNorm is an affine map per channel, `y = (x − μ)·γ/√(σ² + ε) + β`; after a
convolution it can be absorbed into the convolution's weights and bias, which saves one full pass
over every activation. The training model is never touched: `fold_batchnorms` works on a deep copy.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

_CONVS = (nn.Conv2d, nn.Conv3d, nn.ConvTranspose2d, nn.ConvTranspose3d)
_NORMS = (nn.BatchNorm2d, nn.BatchNorm3d)


def fold_conv_bn(conv: nn.Module, bn: nn.Module) -> nn.Module:
    """A new convolution equal to `bn(conv(x))` with BN's running statistics (eval semantics).

    Works for Conv2d/3d (weight `(out, in/groups, k…)`) and ConvTranspose2d/3d (weight
    `(in, out/groups, k…)`, ungrouped); the result always carries a bias.
    """
    if not isinstance(conv, _CONVS) or not isinstance(bn, _NORMS):
        raise TypeError(f"cannot fold {type(bn).__name__} into {type(conv).__name__}")
    transposed = isinstance(conv, (nn.ConvTranspose2d, nn.ConvTranspose3d))
    if transposed and conv.groups != 1:
        raise ValueError(f"folding into a grouped transposed convolution is not supported (groups={conv.groups})")
    out_channels = conv.out_channels
    if bn.num_features != out_channels or bn.running_mean is None or bn.running_var is None:
        raise ValueError(
            f"BatchNorm with {bn.num_features} features and running statistics expected after a "
            f"convolution with {out_channels} output channels"
        )
    fused = copy.deepcopy(conv)
    with torch.no_grad():
        scale = bn.running_var.double().add(bn.eps).rsqrt()
        if bn.weight is not None:
            scale = scale * bn.weight.double()
        shape = [1] * conv.weight.dim()
        shape[1 if transposed else 0] = out_channels
        weight = conv.weight.double() * scale.reshape(shape)
        bias = conv.bias.double() if conv.bias is not None else torch.zeros_like(scale)
        bias = (bias - bn.running_mean.double()) * scale
        if bn.bias is not None:
            bias = bias + bn.bias.double()
        fused.weight = nn.Parameter(weight.to(conv.weight.dtype), requires_grad=False)
        fused.bias = nn.Parameter(bias.to(conv.weight.dtype), requires_grad=False)
    return fused


def fold_batchnorms(module: nn.Module) -> nn.Module:
    """A deep copy of `module` in eval mode in which every `Sequential(…, conv, BN, …)` pair is one conv.

    The BN's place in the Sequential is taken by `nn.Identity`, so indices (and what follows, such
    as the ReLU) stay where they were. BatchNorms that do not follow a convolution are kept.
    """
    folded = copy.deepcopy(module).eval()
    for sequential in [m for m in folded.modules() if isinstance(m, nn.Sequential)]:
        for index in range(len(sequential) - 1):
            conv, bn = sequential[index], sequential[index + 1]
            if isinstance(conv, _CONVS) and isinstance(bn, _NORMS):
                sequential[index] = fold_conv_bn(conv, bn)
                sequential[index + 1] = nn.Identity()
    return folded
