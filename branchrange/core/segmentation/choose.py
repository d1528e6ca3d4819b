"""`make_segmenter`: the segmenter a name asks for — 'learned', 'learned:BUNDLE' (a fine-tuned model bundle),
'structure', 'geometric' or 'onnx:FILE' (your own model) — and `SegmenterConfig`, the `[segmenter]` section that
names it with the settings of each."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from branchrange.core.segmentation.learned import LearnedSegmenter, LearnedSegmenterConfig
from branchrange.core.segmentation.onnx_model import OnnxSegmenter, OnnxSegmenterConfig, OnnxSegmenterError
from branchrange.core.segmentation.segmenter import GeometricSegmenter, GeometricSegmenterConfig, Segmenter
from branchrange.core.segmentation.structure import StructureSegmenter, StructureSegmenterConfig
from branchrange.core.settings_check import Checks, ConfigError

#: The segmenters that ship with the package, by name; the first is the default.
BUILTIN_SEGMENTERS = ("learned", "structure", "geometric")
DEFAULT_SEGMENTER = BUILTIN_SEGMENTERS[0]
#: The names `make_segmenter` accepts, for help texts and error messages.
SEGMENTER_NAMES = (
    "'learned', 'geometric', 'structure' or 'onnx:FILE' (an ONNX YOLOv8-seg or per-pixel-logits model); "
    "'learned:BUNDLE' for a model bundle of train-segmenter --coco"
)
#: the prefixes of names that carry a path: your own ONNX model, a fine-tuned BranchNet's bundle
_WITH_PATH = ("onnx:", "learned:")


def check_segmenter_name(name: str) -> str:
    """`name` itself when it has an accepted form (the file is checked when the model is loaded)."""
    if name in BUILTIN_SEGMENTERS or any(name.startswith(p) and len(name) > len(p) for p in _WITH_PATH):
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
    if name.startswith("learned:"):  # the bundle in place of [segmenter.learned] model, its other settings kept
        return LearnedSegmenter(replace(learned, model=name[len("learned:") :], precision="fp32"))
    return OnnxSegmenter(name[len("onnx:") :], onnx)


@dataclass(frozen=True)
class SegmenterConfig(OnnxSegmenterConfig):
    """Which segmenter finds branches when no mask is given, and the settings of each.

    `model`: 'learned' (the default: the shipped BranchNet network, `[segmenter.learned]`), 'learned:BUNDLE' (a
    model bundle fine-tuned on your labels, `train-segmenter --coco`; `[segmenter.learned]`'s other settings),
    'structure' (built in, 3D structure), 'geometric' (the older built-in one) or 'onnx:FILE' (your ONNX model,
    YOLOv8-seg or per-pixel logits). Your model's settings are the other `[segmenter]` keys
    (`OnnxSegmenterConfig`: `branch_classes` / `trunk_classes`, the model's class ids for branch and
    trunk; `score_threshold`, …); the built-in segmenters' are
    the sub-tables `[segmenter.learned]` (`LearnedSegmenterConfig`), `[segmenter.structure]`
    (`StructureSegmenterConfig`) and `[segmenter.geometric]` (`GeometricSegmenterConfig`).
    """

    section = "segmenter"
    error = ConfigError

    model: str = DEFAULT_SEGMENTER
    structure: StructureSegmenterConfig = field(default_factory=StructureSegmenterConfig)
    geometric: GeometricSegmenterConfig = field(default_factory=GeometricSegmenterConfig)
    learned: LearnedSegmenterConfig = field(default_factory=LearnedSegmenterConfig)

    def checks(self) -> Checks:
        """The model's settings and the model's name (its file is checked when it is loaded)."""
        try:
            named = bool(check_segmenter_name(self.model))
        except ValueError:
            named = False
        return {**super().checks(), "model": (named, SEGMENTER_NAMES)}

    def build(self, name: str | None = None) -> Segmenter:
        """The segmenter `name` names ('structure', 'geometric', 'onnx:FILE'; default `model`) with
        its settings from this section; `OnnxSegmenterError` for a model that cannot be loaded."""
        return make_segmenter(name or self.model, self.geometric, self, self.structure, self.learned)
