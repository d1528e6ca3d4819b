"""Writing a model bundle's manifest (`branchrange.core.segmentation.bundle` reads and checks it at run time).

The fine-tune loop (`branchrange.learning.finetune`) writes the bundle's files, then this manifest over them:
their SHA-256, the class set and the input the network takes, so a loader can refuse a truncated copy or a
bundle made for another version's segmenter before any weight is used.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from branchrange.core.segmentation.bundle import BUNDLE_FORMAT, MANIFEST_NAME, MODEL_NAME
from branchrange.core.segmentation.network_input import CLASSES, IN_CHANNELS, STRIDE
from branchrange.core.segmentation.onnx_model import OnnxSegmenterError
from stereo.weights import sha256_of


def bundle_input(frame_sizes: list[tuple[int, int]]) -> dict[str, Any]:
    """The manifest's "input": what the network takes, and the (width, height) px of the frames it was tuned on."""
    return {
        "channels": IN_CHANNELS,
        "stride": STRIDE,
        "channel_order": ["red", "green", "blue", "disparity / its 95th percentile", "disparity valid"],
        "frame_sizes": [list(size) for size in sorted(set(frame_sizes))],
    }


def write_manifest(folder: Path, frame_sizes: list[tuple[int, int]], version: str) -> dict[str, Any]:
    """Write `MANIFEST_NAME` over every other file in `folder` (their SHA-256) and return it."""
    files = {p.name: sha256_of(p) for p in sorted(folder.iterdir()) if p.is_file() and p.name != MANIFEST_NAME}
    if MODEL_NAME not in files:
        raise OnnxSegmenterError(f"{folder}: no {MODEL_NAME} to bundle")
    manifest = {
        "format": BUNDLE_FORMAT,
        "model": "BranchNet",
        "classes": list(CLASSES),
        "input": bundle_input(frame_sizes),
        "onnx": MODEL_NAME,
        "files": files,
        "created": datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z"),
        "branchrange": version,
    }
    (folder / MANIFEST_NAME).write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    return manifest
