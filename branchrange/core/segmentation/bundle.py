"""A model bundle: one folder holding a fine-tuned `BranchNet` and everything that says what it is.

Layout (`branchrange train-segmenter --coco … --out DIR` writes it with `branchrange.learning.bundle_writer`;
`--segmenter learned:DIR` and `[segmenter.learned] model = "DIR"` load it):

```
DIR/manifest.json        format, class set, input (channels, stride, frame sizes), the SHA-256 of every file below
DIR/branchnet.onnx       the network, run by onnxruntime
DIR/branchnet.json       its metadata: config, the weights it started from, confidence calibrations (the held-out
                         frames' table), validation figures — the same keys as the shipped model's JSON
DIR/branchnet_int8.onnx  with --int8: its statically quantized copy (~1.4× faster on CPU), with its own
DIR/branchnet_int8.json  calibration; `precision = "int8"` runs it
DIR/branchnet.pt         the torch weights (batch norms folded: `branchrange.learning.from_onnx`), to fine-tune further
DIR/metrics.json         held-out frames before (the starting model) and after, synthetic validation IoU
DIR/metrics.csv          the training curve's rows; DIR/training_curve.png its plot
```

Loading checks, before any weight is used: the manifest's format, that its class set and input are the
ones this version's segmenter feeds and reads (`CLASSES`, `IN_CHANNELS`, `STRIDE`), and that every file
listed has the SHA-256 the manifest records — a truncated copy or an edited calibration is refused, each
with an `OnnxSegmenterError` that says what differs.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from branchrange.core.segmentation.network_input import CLASSES, IN_CHANNELS, STRIDE
from branchrange.core.segmentation.onnx_model import OnnxSegmenterError
from stereo.weights import sha256_of

MANIFEST_NAME = "manifest.json"
BUNDLE_FORMAT = "branchrange/segmenter-bundle/v1"
MODEL_NAME = "branchnet.onnx"
#: the bundle's int8 copy (`train-segmenter --coco … --int8`: `branchrange.learning.quantize`, calibrated on its own)
INT8_MODEL_NAME = "branchnet_int8.onnx"


def read_manifest(folder: Path) -> dict[str, Any]:
    """The manifest of the bundle `folder`, checked for its format, class set and input (not its files)."""
    path = folder / MANIFEST_NAME
    if not path.is_file():
        raise OnnxSegmenterError(
            f"learned segmenter: {folder} is a folder but not a model bundle (no {MANIFEST_NAME}; "
            "train-segmenter --coco … --out DIR writes one)"
        )
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise OnnxSegmenterError(f"learned segmenter: {path} is not readable JSON ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != BUNDLE_FORMAT:
        found = manifest.get("format") if isinstance(manifest, dict) else None
        raise OnnxSegmenterError(f"learned segmenter: {path}: format {found!r}, expected {BUNDLE_FORMAT!r}")
    if manifest.get("classes") != list(CLASSES):
        raise OnnxSegmenterError(
            f"learned segmenter: bundle {folder} was made for the classes {manifest.get('classes')}; this "
            f"segmenter reads {list(CLASSES)} — fine-tune again from this version's model"
        )
    given = manifest.get("input")
    given = given if isinstance(given, dict) else {}
    wanted = {"channels": IN_CHANNELS, "stride": STRIDE}
    if {k: given.get(k) for k in wanted} != wanted:
        raise OnnxSegmenterError(
            f"learned segmenter: bundle {folder} was made for input { ({k: given.get(k) for k in wanted}) }; this "
            f"segmenter feeds {wanted} (image + disparity) — fine-tune again from this version's model"
        )
    return manifest


def bundle_model(folder: Path, precision: str = "fp32") -> Path:
    """The ONNX file of the bundle `folder` of `precision` ("fp32", or "int8": its quantized copy), after
    `read_manifest`'s checks and the SHA-256 of every file it lists; `OnnxSegmenterError` saying which file is
    missing or differs, or that the bundle has no int8 copy."""
    manifest = read_manifest(folder)
    files = manifest.get("files")
    if not isinstance(files, dict) or MODEL_NAME not in files:
        raise OnnxSegmenterError(f"learned segmenter: {folder / MANIFEST_NAME} lists no {MODEL_NAME}")
    model_name = INT8_MODEL_NAME if precision == "int8" else MODEL_NAME
    if model_name not in files:
        raise OnnxSegmenterError(
            f"learned segmenter: bundle {folder} has no int8 copy ({INT8_MODEL_NAME}): fine-tune with --int8, or "
            'set [segmenter.learned] precision = "fp32" to run its fp32 model'
        )
    for name, expected in files.items():
        path = folder / name
        if not path.is_file():
            raise OnnxSegmenterError(f"learned segmenter: bundle {folder} lacks {name}, which its manifest lists")
        found = sha256_of(path)
        if found != expected:
            raise OnnxSegmenterError(
                f"learned segmenter: {path} has SHA-256 {found}, the bundle's manifest records {expected}: the "
                "file is truncated or changed since it was trained (copy the whole bundle again)"
            )
    return folder / model_name
