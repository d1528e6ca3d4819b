"""`make_segmenter`: the segmenter a name asks for — 'learned', 'structure', 'geometric' or 'onnx:FILE'
(your own model)."""

from __future__ import annotations

from branchrange.core.segmentation.learned import LearnedSegmenter, LearnedSegmenterConfig
from branchrange.core.segmentation.onnx_model import OnnxSegmenter, OnnxSegmenterConfig, OnnxSegmenterError
from branchrange.core.segmentation.segmenter import GeometricSegmenter, GeometricSegmenterConfig, Segmenter
from branchrange.core.segmentation.structure import StructureSegmenter, StructureSegmenterConfig

#: The segmenters that ship with the package, by name; the first is the default.
BUILTIN_SEGMENTERS = ("learned", "structure", "geometric")
DEFAULT_SEGMENTER = BUILTIN_SEGMENTERS[0]
#: The names `make_segmenter` accepts, for help texts and error messages.
SEGMENTER_NAMES = "'learned', 'geometric', 'structure' or 'onnx:FILE' (an ONNX YOLOv8-seg or per-pixel-logits model)"


def check_segmenter_name(name: str) -> str:
    """`name` itself when it has an accepted form (the file is checked when the model is loaded)."""
    if name in BUILTIN_SEGMENTERS or (name.startswith("onnx:") and len(name) > len("onnx:")):
        return name
    raise OnnxSegmenterError(f"segmenter {name!r}: expected {SEGMENTER_NAMES}")


def make_segmenter(
    name: str,
    geometric: GeometricSegmenterConfig = GeometricSegmenterConfig(),
    onnx: OnnxSegmenterConfig = OnnxSegmenterConfig(),
    structure: StructureSegmenterConfig = StructureSegmenterConfig(),
    learned: LearnedSegmenterConfig = LearnedSegmenterConfig(),
) -> Segmenter:
    """The segmenter `name` names, built with its settings; `OnnxSegmenterError` for a bad name or model."""
    check_segmenter_name(name)
    if name == "geometric":
        return GeometricSegmenter(geometric)
    if name == "learned":
        return LearnedSegmenter(learned)
    if name == "structure":
        return StructureSegmenter(structure)
    return OnnxSegmenter(name[len("onnx:") :], onnx)
