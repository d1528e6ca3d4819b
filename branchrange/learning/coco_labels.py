"""A user's labelled frames — COCO instance segmentation, as `branchrange export-frames` writes them and CVAT or
Label Studio give them back corrected — as `BranchNet` training samples.

What is read, per image of `annotations.json`:
- the image itself, from `--images` by its `file_name` (`uint8 H×W×3` RGB);
- its stereo, from `STEREO_DIR` beside the images folder: `<stem>.npz` with `disparity` (`float32 H×W` px,
  what the pipeline computed when the frame was exported), `confidence` (`H×W` in [0, 1]) and `camera`
  (focal px, baseline m, cx, cy). `BranchNet` sees disparity beside the colours, so a frame without it
  cannot be trained on; labelling tools drop extra image fields, so the stereo is found by file name;
- its labels, decoded by pycocotools (polygons, RLE compressed or not): categories are matched by name
  (`LABELLED_CLASSES`, case ignored); other categories are left out and reported; `iscrowd` regions are
  `IGNORE` (neither answer penalised); a branch drawn over the trunk is branch (a stem in front of it).
  Pixels no annotation covers are background: the labels are taken as complete, as a corrected
  pre-annotation is.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from branchrange.core.geometry import StereoGeometry
from branchrange.learning.samples import BRANCH, IGNORE, TRUNK

#: the folder beside the images that holds each frame's stereo (`<stem>.npz`), as `export-frames` writes it
STEREO_DIR = "stereo"
#: category name → the class `BranchNet` learns for it
LABELLED_CLASSES = {"trunk": TRUNK, "branch": BRANCH}


class LabelsError(ValueError):
    """The labelled data set cannot be trained on (unreadable file, missing image or stereo, no branch or
    trunk category, pycocotools absent); the message names the file and what to do."""


@dataclass(frozen=True)
class LabelledSample:
    """One labelled frame: its `file_name`, COCO image id, the training sample (`left` `uint8 H×W×3`,
    `disparity` `float32 H×W` px, `classes` `uint8 H×W`, `instances` `uint16 H×W`: branches 1..K, as
    `branchrange.learning.samples` samples), the stereo confidence `H×W` and the camera it was recorded with."""

    name: str
    image_id: int
    sample: dict[str, np.ndarray]
    confidence: np.ndarray
    geometry: StereoGeometry


def write_frame_stereo(path: Path, disparity: np.ndarray, confidence: np.ndarray, geometry: StereoGeometry) -> None:
    """Write one frame's stereo as `read_frame_stereo` reads it (a compressed `.npz`)."""
    camera = np.array([geometry.focal_px, geometry.baseline_m, geometry.cx, geometry.cy], dtype=np.float64)
    np.savez_compressed(
        path,
        disparity=np.asarray(disparity, dtype=np.float32),
        confidence=np.asarray(confidence, dtype=np.float16),
        camera=camera,
    )


def read_frame_stereo(path: Path, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, StereoGeometry]:
    """(disparity `float32 H×W` px, confidence `float32 H×W`, camera) of one frame whose image is `shape`
    (H, W); `LabelsError` when the file is missing, unreadable or of another size."""
    if not path.is_file():
        raise LabelsError(
            f"{path}: no stereo for this frame. train-segmenter needs each frame's disparity beside its image "
            f"(export-frames writes it in {STEREO_DIR}/); pass --stereo DIR if it lives elsewhere"
        )
    try:
        with np.load(path, allow_pickle=False) as data:
            disparity = np.asarray(data["disparity"], dtype=np.float32)
            confidence = np.asarray(data["confidence"], dtype=np.float32)
            focal, baseline, cx, cy = (float(v) for v in data["camera"])
        geometry = StereoGeometry(focal, baseline, cx, cy)
    except (OSError, ValueError, KeyError) as exc:
        raise LabelsError(f"{path}: not a frame's stereo as export-frames writes it ({exc})") from None
    if disparity.shape != shape or confidence.shape != shape:
        raise LabelsError(f"{path}: disparity {disparity.shape[::-1]} px, but its image is {shape[::-1]} px")
    return disparity, confidence, geometry


def _coco_api() -> Any:
    """pycocotools.coco, or `LabelsError` saying how to install it."""
    try:
        from pycocotools import coco
    except ImportError:
        raise LabelsError(
            "train-segmenter reads COCO labels with pycocotools, which is not installed: "
            "pip install 'branchrange[coco]' (or pip install pycocotools)"
        ) from None
    return coco


def load_coco(annotations: Path) -> Any:
    """The pycocotools `COCO` index of `annotations` (its progress lines kept off stdout); `LabelsError` when
    the file is missing or not a COCO data set."""
    coco = _coco_api()
    if not annotations.is_file():
        raise LabelsError(f"{annotations}: no such annotations file (expected COCO instance segmentation JSON)")
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            return coco.COCO(str(annotations))
    except (OSError, ValueError, KeyError, TypeError, AssertionError) as exc:
        raise LabelsError(
            f"{annotations}: not a COCO instance-segmentation file ({type(exc).__name__}: {exc})"
        ) from None


def labelled_categories(dataset: Any, log: Callable[[str], object]) -> dict[int, int]:
    """COCO category id → `BranchNet` class for the categories named in `LABELLED_CLASSES`; the others are
    reported through `log` and left out. `LabelsError` when neither branch nor trunk is there."""
    found: dict[int, int] = {}
    others = []
    for category in dataset.loadCats(dataset.getCatIds()):
        name = str(category.get("name", "")).strip().lower()
        if name in LABELLED_CLASSES:
            found[int(category["id"])] = LABELLED_CLASSES[name]
        else:
            others.append(str(category.get("name")))
    if not found:
        raise LabelsError(
            f"no 'branch' or 'trunk' category among {others or 'none'}: BranchNet learns those two classes "
            "(rename the label classes in the labelling tool)"
        )
    if others:
        log(f"categories {others} left out: BranchNet learns branch and trunk (their pixels count as background)")
    return found


def label_maps(dataset: Any, image: dict[str, Any], categories: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(classes `uint8 H×W`, branch instances `uint16 H×W`) of one COCO image record's annotations (see the
    module docstring for the order); `LabelsError` naming an annotation pycocotools cannot decode."""
    shape = (int(image["height"]), int(image["width"]))
    classes = np.zeros(shape, dtype=np.uint8)
    instances = np.zeros(shape, dtype=np.uint16)
    annotations = [
        a for a in dataset.loadAnns(dataset.getAnnIds(imgIds=[image["id"]])) if a["category_id"] in categories
    ]
    crowd = [a for a in annotations if a.get("iscrowd", 0)]
    trunk = [a for a in annotations if not a.get("iscrowd", 0) and categories[a["category_id"]] == TRUNK]
    branch = [a for a in annotations if not a.get("iscrowd", 0) and categories[a["category_id"]] == BRANCH]
    for number, annotation in enumerate([*trunk, *branch, *crowd]):
        try:
            mask = dataset.annToMask(annotation).astype(bool)
        except (ValueError, TypeError, KeyError, IndexError) as exc:
            raise LabelsError(
                f"annotation {annotation.get('id')}: its segmentation cannot be decoded ({exc})"
            ) from None
        if mask.shape != shape:
            raise LabelsError(
                f"annotation {annotation.get('id')}: mask {mask.shape[::-1]} px on an image {shape[::-1]}"
            )
        if annotation.get("iscrowd", 0):
            classes[mask] = IGNORE
            continue
        label = categories[annotation["category_id"]]
        classes[mask] = label
        if label == BRANCH:
            instances[mask] = number - len(trunk) + 1
    return classes, instances


def read_labelled_frames(
    annotations: Path, images: Path, stereo: Path | None = None, log: Callable[[str], object] = print
) -> list[LabelledSample]:
    """Every image of the COCO file `annotations` as a `LabelledSample`, in image-id order: images from the
    folder `images`, stereo from `stereo` (default: `STEREO_DIR` beside `images`). `LabelsError` for what
    cannot be trained on (the message names the file)."""
    from stereo.io import read_rgb

    dataset = load_coco(annotations)
    categories = labelled_categories(dataset, log)
    stereo = images.parent / STEREO_DIR if stereo is None else stereo
    samples = []
    for image_id in sorted(dataset.getImgIds()):
        image = dataset.loadImgs([image_id])[0]
        name = str(image.get("file_name", ""))
        path = images / Path(name).name
        try:
            left = read_rgb(path)
        except (OSError, ValueError) as exc:
            raise LabelsError(f"{path}: image {image_id} ({name!r}) cannot be read ({exc})") from None
        if left.shape[:2] != (image.get("height"), image.get("width")):
            raise LabelsError(
                f"{path}: {left.shape[1]}×{left.shape[0]} px, but {annotations.name} says "
                f"{image.get('width')}×{image.get('height')}"
            )
        disparity, confidence, geometry = read_frame_stereo(stereo / f"{Path(name).stem}.npz", left.shape[:2])
        classes, instances = label_maps(dataset, image, categories)
        sample = {"left": left, "disparity": disparity, "classes": classes, "instances": instances}
        samples.append(LabelledSample(name, int(image_id), sample, confidence, geometry))
    if not samples:
        raise LabelsError(f"{annotations}: no images to train on")
    return samples


def split_by_image(count: int, holdout_share: float, seed: int) -> tuple[list[int], list[int]]:
    """(training, held-out) positions of `count` frames: a seeded shuffle, round(`holdout_share` × count)
    held out — at least one when the share is above 0 and two frames or more exist, and at least one kept
    to train on. Frames, not crops, are split: crops of one frame are alike."""
    order = np.random.default_rng(seed).permutation(count)
    held = round(holdout_share * count)
    if holdout_share > 0 and count >= 2:
        held = min(max(held, 1), count - 1)
    held_out = sorted(int(i) for i in order[:held])
    return sorted(int(i) for i in order[held:]), held_out
