"""Frames and their masks as a COCO instance-segmentation data set, for labelling tools to correct.

Layout of `DIR` (what CVAT's "COCO 1.0" import and Label Studio's COCO converter read):

```
DIR/images/frame_000123.png       the frames' (rectified) left views, lossless; each image's `file_name`
                                  is the bare name, its index in the source (and `timestamp_ns`) beside it
DIR/annotations.json              COCO: info, licenses, images, categories branch (1) / trunk (2),
                                  one annotation per instance, its mask as COCO RLE (exact)
DIR/annotations_polygons.json     the same with each mask as polygons (its outer outlines)
DIR/stereo/frame_000123.npz       the frame's disparity, stereo confidence and camera, which
                                  `train-segmenter` reads beside the labels (`coco_labels`)
```

Why two files: the masks are pre-annotations a person corrects, so they must arrive as they are.
COCO's run-length encoding (`segmentation` = {"size": [h, w], "counts": "…"}, pycocotools' compressed
form) is exact, and CVAT imports it as a mask (iscrowd is 0: each is one object, which trainers keep).
Label Studio's COCO converter reads polygons only (it skips RLE), so the second file gives each mask's
outer outlines (OpenCV contours at twice the resolution, see `_outlines`; holes are lost there).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from branchrange.core.geometry import StereoGeometry
from branchrange.core.masks import BranchMasks
from branchrange.learning.coco_labels import STEREO_DIR, write_frame_stereo

#: COCO category ids of the two classes the pre-annotations carry.
BRANCH_CATEGORY, TRUNK_CATEGORY = 1, 2
CATEGORIES = (
    {"id": BRANCH_CATEGORY, "name": "branch", "supercategory": "tree"},
    {"id": TRUNK_CATEGORY, "name": "trunk", "supercategory": "tree"},
)
ANNOTATIONS_NAME = "annotations.json"
POLYGONS_NAME = "annotations_polygons.json"
IMAGES_DIR = "images"


class CocoExportError(OSError):
    """The data set cannot be written (pycocotools missing, an image not writable); the message says which."""


@dataclass(frozen=True)
class LabelledFrame:
    """One frame to label: its left view (`uint8 H×W×3` RGB), today's masks on it (None: nothing to
    segment, e.g. no valid disparity), its index and capture time (ns) in its source; and, for fine-tuning
    on it later, its disparity (`float32 H×W` px), stereo confidence (`H×W`) and camera (None: not written)."""

    image: np.ndarray
    masks: BranchMasks | None
    index: int
    timestamp_ns: int
    disparity: np.ndarray | None = None
    confidence: np.ndarray | None = None
    geometry: StereoGeometry | None = None

    @property
    def file_name(self) -> str:
        """The image's name, after the frame's index in its source; a bare name in `IMAGES_DIR`, as COCO's
        own sets have it and as CVAT matches an uploaded annotation file to a task's images."""
        return f"frame_{self.index:06d}.png"


def _mask_api() -> Any:
    """pycocotools.mask, or `CocoExportError` saying how to install it."""
    try:
        from pycocotools import mask
    except ImportError:
        raise CocoExportError(
            "export-frames writes COCO masks with pycocotools, which is not installed: "
            "pip install 'branchrange[coco]' (or pip install pycocotools)"
        ) from None
    return mask


def _instances(masks: BranchMasks | None) -> list[tuple[int, np.ndarray]]:
    """(COCO category, boolean `H×W` mask) of every branch instance, then the trunk."""
    if masks is None:
        return []
    found = [(BRANCH_CATEGORY, masks.branch(i)) for i in masks.branch_ids()]
    trunk = masks.trunk()
    return found + ([(TRUNK_CATEGORY, trunk)] if trunk is not None else [])


def _outlines(mask: np.ndarray) -> list[list[float]]:
    """A mask's outer outlines as COCO polygons `[x0, y0, x1, y1, …]`, 3 points or more.

    Traced on the mask at twice its resolution, a vertex at the middle of a boundary half-pixel: a stem
    one pixel wide keeps a polygon half a pixel wide around its pixel centres, which COCO rasterises back
    to those pixels (traced through the pixel centres it would have no width and vanish). Only holes are
    lost: on the synthetic tree's masks the polygons give back IoU ≥ 0.98 of each."""
    doubled = cv2.resize(mask.astype(np.uint8), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    contours, _ = cv2.findContours(doubled, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    return [((c.reshape(-1).astype(float) + 0.5) / 2).tolist() for c in contours if len(c) >= 3]


#: COCO annotations (or images) as JSON-ready dicts.
Records = list[dict[str, Any]]


def _annotations(frame: LabelledFrame, image_id: int, first_id: int, mask_api: Any) -> tuple[Records, Records]:
    """The frame's annotations twice: segmentation as RLE, and as polygons (instances without one left out)."""
    rle_annotations: Records = []
    polygon_annotations: Records = []
    for offset, (category, mask) in enumerate(_instances(frame.masks)):
        rle = mask_api.encode(np.asfortranarray(mask.astype(np.uint8)))
        common = {
            "id": first_id + offset,
            "image_id": image_id,
            "category_id": category,
            "area": float(mask_api.area(rle)),
            "bbox": [float(v) for v in mask_api.toBbox(rle)],
            "iscrowd": 0,
        }
        segmentation = {"size": list(rle["size"]), "counts": rle["counts"].decode("ascii")}
        rle_annotations.append({**common, "segmentation": segmentation})
        polygons = _outlines(mask)
        if polygons:
            polygon_annotations.append({**common, "segmentation": polygons})
    return rle_annotations, polygon_annotations


def _write_image(path: Path, image: np.ndarray) -> None:
    """Write an RGB image as PNG (BGR at the OpenCV call); `CocoExportError` when it cannot be."""
    if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise CocoExportError(f"{path}: could not be written (expected a writable directory)")


def write_coco(out_dir: str | Path, frames: Iterable[LabelledFrame], source: str, version: str) -> Path:
    """Write `frames` as the data set of the module docstring in `out_dir` (created; files of an earlier
    export with the same names replaced) and return the path of annotations.json.

    `source` (the recording or bag the frames came from) and `version` (of branchrange) go into the
    info block. Raises `CocoExportError` when pycocotools is missing or a file cannot be written.
    """
    mask_api = _mask_api()
    out = Path(out_dir)
    (out / IMAGES_DIR).mkdir(parents=True, exist_ok=True)
    images: Records = []
    rle_annotations: Records = []
    polygon_annotations: Records = []
    for image_id, frame in enumerate(frames, start=1):
        height, width = frame.image.shape[:2]
        _write_image(out / IMAGES_DIR / frame.file_name, frame.image)
        if frame.disparity is not None and frame.confidence is not None and frame.geometry is not None:
            (out / STEREO_DIR).mkdir(exist_ok=True)
            stereo = out / STEREO_DIR / f"{Path(frame.file_name).stem}.npz"
            write_frame_stereo(stereo, frame.disparity, frame.confidence, frame.geometry)
        images.append(
            {
                "id": image_id,
                "file_name": frame.file_name,
                "width": width,
                "height": height,
                "license": 1,
                "frame_index": frame.index,
                "timestamp_ns": frame.timestamp_ns,
            }
        )
        rle, polygons = _annotations(frame, image_id, len(rle_annotations) + 1, mask_api)
        rle_annotations += rle
        polygon_annotations += polygons
    now = datetime.now(UTC)
    header = {
        "info": {
            "description": f"BranchRange frames for labelling from {source}, pre-annotated with its masks",
            "version": version,
            "year": now.year,
            "contributor": "branchrange export-frames",
            "date_created": now.isoformat(timespec="seconds").replace("+00:00", "Z"),
            "url": "",
        },
        "licenses": [{"id": 1, "name": "the recording owner's terms", "url": ""}],
        "images": images,
        "categories": list(CATEGORIES),
    }
    for name, found in ((ANNOTATIONS_NAME, rle_annotations), (POLYGONS_NAME, polygon_annotations)):
        (out / name).write_text(json.dumps({**header, "annotations": found}) + "\n", encoding="utf-8")
    return out / ANNOTATIONS_NAME
