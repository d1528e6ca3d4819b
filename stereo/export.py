"""ONNX export of EMCStereo's inference graph, for ONNX Runtime (the `onnx` backend).

The exported graph is the fast inference path (`FastInference`) with PyTorch's public operators
only, traced at one padded input size and one disparity range: inputs `left`, `right`
ImageNet-normalised float32 (1, 3, H, W); outputs `disparity` and `confidence` float32 (1, H, W).
The size and range are stored in the model's metadata (`METADATA_KEYS`) for the backend to read.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import torch
from torch import nn

from .model import EMCStereo
from .model.fast_inference import FastInference
from .model.stages import check_input_size

#: Metadata the exported file carries: padded input height and width, disparity range (px).
METADATA_KEYS = ("height", "width", "max_disp")
OPSET = 17


class ExportError(ValueError):
    """A model cannot be exported as asked (size, range or missing ONNX package); the message says which."""


class _FixedRangeGraph(nn.Module):
    """`FastInference` at one disparity range, as the two-input, two-output module ONNX sees."""

    def __init__(self, model: EMCStereo, disparities: int) -> None:
        super().__init__()
        self.fast = FastInference(model, use_onednn=False)
        self.disparities = disparities

    def forward(self, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.fast(left, right, self.disparities)


def export_onnx(
    model: EMCStereo, path: str | os.PathLike[str], height: int, width: int, max_disp: int | None = None
) -> Path:
    """Write `model`'s inference graph for padded `height × width` inputs to an ONNX file; returns its path.

    `height` and `width` must be multiples of 32 and ≥ 256 (pad images as `stereo.padding` does);
    `max_disp` (default the model's) a multiple of 16 within the model's range.
    """
    try:
        import onnx
    except ImportError as exc:
        raise ExportError("ONNX export needs the 'onnx' package (pip install 'branchrange[onnx]')") from exc
    disparities = model.max_disp if max_disp is None else max_disp
    if disparities <= 0 or disparities % 16 or disparities > model.max_disp:
        raise ExportError(f"max_disp must be a multiple of 16 in (0, {model.max_disp}], got {max_disp}")
    example = torch.zeros(1, 3, height, width)
    try:
        check_input_size(example, example)
    except ValueError as exc:
        raise ExportError(f"cannot export for {height}×{width}: {exc}") from exc
    path = Path(path)
    graph = _FixedRangeGraph(model, disparities).cpu()  # a folded copy: `model` itself stays as it was
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer warnings about Python ints from shapes: the size is fixed on purpose
        torch.onnx.export(
            graph,
            (example, example),
            str(path),
            input_names=["left", "right"],
            output_names=["disparity", "confidence"],
            opset_version=OPSET,
            dynamo=False,
        )
    exported = onnx.load(str(path))
    for key, value in zip(METADATA_KEYS, (height, width, disparities)):
        exported.metadata_props.add(key=key, value=str(value))
    onnx.save(exported, str(path))
    return path
