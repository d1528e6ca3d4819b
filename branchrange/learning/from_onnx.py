"""A `BranchNet` in torch from its ONNX file, so a fine-tune starts from exactly the weights that ship.

The package ships only the ONNX file (under 1 MB; the torch checkpoint of the training run is not kept).
torch's export folds every batch norm into the convolution before it: each ONNX `Conv` holds the folded
weights and a bias. Read back in graph order — the order the forward pass runs the convolutions, which
the export traced — each goes into its torch convolution, and the batch norm after it becomes the
identity plus that bias (running mean 0, running variance 1 − eps, scale 1). The network then computes
what the ONNX file computes (checked on a random input before it is handed back). Its batch norms must
stay in eval mode while it is fine-tuned (`branchrange.learning.finetune` keeps them so): their statistics are folded
away, and a few dozen frames in batches of 8 would be too few to measure them again anyway.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from branchrange.core.segmentation.network_input import IN_CHANNELS, STRIDE
from branchrange.core.segmentation.onnx_model import OnnxSegmenterError, onnx_session
from branchrange.learning.branchnet import BranchNet

#: the largest difference (logits) between the ONNX file and the network read from it on a random input
MATCH_TOLERANCE = 1e-3


def _conv_order(model: BranchNet) -> list[str]:
    """Names of `model`'s convolutions in the order its forward pass runs them."""
    names = {module: name for name, module in model.named_modules()}
    order: list[str] = []
    hooks = [
        m.register_forward_hook(lambda module, _i, _o: order.append(names[module]))
        for m in model.modules()
        if isinstance(m, nn.Conv2d)
    ]
    with torch.inference_mode():
        model.eval()(torch.zeros(1, IN_CHANNELS, 2 * STRIDE, 2 * STRIDE))
    for hook in hooks:
        hook.remove()
    return order


def branchnet_from_onnx(path: Path, width: int, fine_width: int, deep_blocks: int = 0) -> BranchNet:
    """The `BranchNet(width, fine_width, deep_blocks)` whose weights are those of the ONNX file `path` (see the module
    docstring), in eval mode; `OnnxSegmenterError` when the file is not such a network."""
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError:
        raise OnnxSegmenterError(
            "fine-tuning reads the model's ONNX weights with the onnx package: pip install 'branchrange[onnx]'"
        ) from None
    try:
        graph = onnx.load(str(path)).graph
    except Exception as exc:  # noqa: BLE001 - onnx raises its own (protobuf) errors for any unreadable file
        raise OnnxSegmenterError(f"{path}: not an ONNX file ({exc})") from None
    weights = {init.name: numpy_helper.to_array(init) for init in graph.initializer}
    convs = [node for node in graph.node if node.op_type == "Conv"]
    model = BranchNet(width, fine_width, deep_blocks)
    order = _conv_order(model)
    modules = dict(model.named_modules())
    if len(convs) != len(order):
        raise OnnxSegmenterError(
            f"{path}: {len(convs)} convolutions, a BranchNet of width {width} (fine {fine_width}) has {len(order)}"
        )
    with torch.no_grad():
        for node, name in zip(convs, order, strict=True):
            conv = modules[name]
            assert isinstance(conv, nn.Conv2d)
            kernel = weights.get(node.input[1])
            bias = weights.get(node.input[2]) if len(node.input) > 2 else None
            if kernel is None or bias is None or kernel.shape != tuple(conv.weight.shape):
                found = None if kernel is None else kernel.shape
                raise OnnxSegmenterError(
                    f"{path}: convolution {node.name or name} has weights {found}, {name} of a BranchNet of width "
                    f"{width} (fine {fine_width}) takes {tuple(conv.weight.shape)} and a folded bias"
                )
            conv.weight.copy_(torch.from_numpy(np.array(kernel)))
            if conv.bias is not None:  # the head's last 1×1 convolution: no batch norm after it
                conv.bias.copy_(torch.from_numpy(np.array(bias)))
                continue
            parent, _, index = name.rpartition(".")
            norm = modules[f"{parent}.{int(index) + 1}"]
            assert isinstance(norm, nn.BatchNorm2d) and norm.running_mean is not None and norm.running_var is not None
            norm.weight.fill_(1.0)
            norm.bias.copy_(torch.from_numpy(np.array(bias)))
            norm.running_mean.zero_()
            norm.running_var.fill_(1.0 - norm.eps)
    _check_matches(model.eval(), path)
    return model


def _check_matches(model: BranchNet, path: Path) -> None:
    """`OnnxSegmenterError` unless `model` and the ONNX file `path` give the same logits on a random input."""
    session = onnx_session(path, threads=1)
    probe = np.random.default_rng(0).normal(size=(1, IN_CHANNELS, 4 * STRIDE, 6 * STRIDE)).astype(np.float32)
    expected = session.run(None, {session.get_inputs()[0].name: probe})[0]
    with torch.inference_mode():
        found = model(torch.from_numpy(probe)).numpy()
    difference = float(np.max(np.abs(found - expected)))
    if not difference <= MATCH_TOLERANCE:
        raise OnnxSegmenterError(
            f"{path}: the network read from it differs from the file by {difference:.3g} in its logits: not a "
            "BranchNet of the width its JSON records"
        )
