"""Branch instance masks: read instance-id PNGs or binary masks, split into instances, validate.

An instance mask is an `H×W` integer image: 0 = background, one id per branch, and optionally one
id (the trunk id, configurable) for the trunk. A binary mask (any non-zero = branch) is split into
its 8-connected components, each one branch; a binary mask knows no trunk.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from branchrange.core.confidence import ConfidenceCalibration, visible_length_factor
from branchrange.core.light_check import LightReading
from branchrange.core.segmentation.ood import OodReading
from branchrange.core.settings_check import Checks, ConfigError, Limit, Settings, one_of

#: The trunk's id in instance masks unless configured otherwise (the synthetic generator's value).
DEFAULT_TRUNK_ID = 65535
#: Ids that are neither branch nor trunk unless configured otherwise: the top of the 16-bit range
#: is reserved for twigs (65534) and leaves (65533), as the synthetic generator writes them.
DEFAULT_IGNORED_IDS: tuple[int, ...] = (65533, 65534)

MaskKind = Literal["auto", "instance", "binary"]


class MaskError(ValueError):
    """A mask that cannot be used: unreadable, wrong size, wrong type, or holding no branch."""


@dataclass(frozen=True)
class MaskCrop:
    """A boolean instance mask held as its bounding window (plus a margin) in a larger image.

    `mask` is the `h×w` boolean window whose pixel (0, 0) is the image's pixel (row `top`, column
    `left`); `image_shape` is the image's (H, W). Why: every per-instance step reads only the
    window, so its cost follows the instance's size, not the frame's.
    """

    mask: np.ndarray
    top: int
    left: int
    image_shape: tuple[int, int]

    @classmethod
    def of(cls, mask: np.ndarray, margin: int = 2) -> MaskCrop:
        """The crop of a whole boolean `H×W` mask: its bounding box grown by `margin` px (clipped)."""
        mask = np.asarray(mask, dtype=bool)
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        if rows.size == 0:
            return cls(np.zeros((0, 0), dtype=bool), 0, 0, mask.shape)
        box = _grown((int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1), margin, mask.shape)
        return cls(mask[box[0] : box[1], box[2] : box[3]], box[0], box[2], mask.shape)

    def pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) `(N,)` int64 image coordinates of the mask's pixels, in row-major order."""
        rows, cols = np.nonzero(self.mask)
        return rows + self.top, cols + self.left

    def window(self, top: int, left: int, height: int, width: int) -> np.ndarray:
        """The mask over another `height×width` window of the image at (`top`, `left`); False outside."""
        out = np.zeros((height, width), dtype=bool)
        r0, c0 = max(top, self.top), max(left, self.left)
        r1 = min(top + height, self.top + self.mask.shape[0])
        c1 = min(left + width, self.left + self.mask.shape[1])
        if r0 < r1 and c0 < c1:
            out[r0 - top : r1 - top, c0 - left : c1 - left] = self.mask[
                r0 - self.top : r1 - self.top, c0 - self.left : c1 - self.left
            ]
        return out

    def contains(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Boolean `(N,)`: whether each image pixel (`rows`, `cols` `(N,)`) is in the mask (False outside it)."""
        r, c = np.asarray(rows, dtype=np.int64) - self.top, np.asarray(cols, dtype=np.int64) - self.left
        h, w = self.mask.shape
        inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        out = np.zeros(r.shape, dtype=bool)
        out[inside] = self.mask[r[inside], c[inside]]
        return out

    def with_mask(self, mask: np.ndarray) -> MaskCrop:
        """The same window holding another boolean mask of its shape (e.g. the eroded one)."""
        return MaskCrop(mask, self.top, self.left, self.image_shape)

    def touches_image_border(self) -> bool:
        """Whether the mask reaches the image's first or last row or column (the image cuts it)."""
        h, w = self.mask.shape
        height, width = self.image_shape
        return bool(
            (self.top == 0 and self.mask[0].any())
            or (self.top + h == height and self.mask[-1].any())
            or (self.left == 0 and self.mask[:, 0].any())
            or (self.left + w == width and self.mask[:, -1].any())
        )

    def full(self) -> np.ndarray:
        """The boolean `H×W` mask of the whole image."""
        return self.window(0, 0, *self.image_shape)

    def distances_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Distance (px) from image pixels (`rows`, `cols` `(N,)`, clipped into the image) to the
        nearest mask pixel: OpenCV's `DIST_L2` 5×5 chamfer distance, as over the whole image.

        Computed over the window spanning the mask and the pixels only: a shortest chamfer path
        steps monotonically toward its end, so it never leaves the bounding box of its two ends.
        """
        height, width = self.image_shape
        rows = np.clip(np.asarray(rows, dtype=np.int64), 0, height - 1)
        cols = np.clip(np.asarray(cols, dtype=np.int64), 0, width - 1)
        r0 = min(self.top, int(rows.min()))
        c0 = min(self.left, int(cols.min()))
        r1 = max(self.top + self.mask.shape[0], int(rows.max()) + 1)
        c1 = max(self.left + self.mask.shape[1], int(cols.max()) + 1)
        outside = ~self.window(r0, c0, r1 - r0, c1 - c0)
        distance = cv2.distanceTransform(outside.astype(np.uint8), cv2.DIST_L2, 5)
        at_points: np.ndarray = distance[rows - r0, cols - c0]
        return at_points


def as_crop(mask: np.ndarray | MaskCrop) -> MaskCrop:
    """`mask` as a `MaskCrop`: unchanged when it is one, else the crop of the boolean `H×W` mask."""
    return mask if isinstance(mask, MaskCrop) else MaskCrop.of(mask)


def _grown(box: tuple[int, int, int, int], margin: int, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """A (row0, row1, col0, col1) half-open box grown by `margin` px on every side, clipped to `shape`."""
    return (
        max(box[0] - margin, 0),
        min(box[1] + margin, shape[0]),
        max(box[2] - margin, 0),
        min(box[3] + margin, shape[1]),
    )


@dataclass(frozen=True)
class InstanceIndex:
    """Every non-zero id of a label image with its pixel count and bounding box, from one pass.

    `ids` ascending `(K,)`; `counts` `(K,)` pixels; `boxes` `(K, 4)` half-open (row0, row1, col0, col1).
    """

    ids: np.ndarray
    counts: np.ndarray
    boxes: np.ndarray

    @classmethod
    def of(cls, labels: np.ndarray) -> InstanceIndex:
        """Index of an integer `H×W` label image in O(pixels).

        The non-zero pixels in row-major order split into runs of one id within one row; a run's
        first and last pixels are its leftmost and rightmost, so per-id extents need only a
        reduction over the runs (far fewer than pixels).
        """
        height, width = labels.shape
        flat = np.ascontiguousarray(labels).ravel()
        where = np.flatnonzero(flat)
        if where.size == 0:
            empty = np.zeros(0, dtype=np.int64)
            return cls(empty, empty, np.zeros((0, 4), dtype=np.int64))
        values = flat[where]
        rows = where // width
        cols = where - rows * width
        breaks = np.flatnonzero((values[1:] != values[:-1]) | (rows[1:] != rows[:-1])) + 1
        starts = np.concatenate(([0], breaks))
        ends = np.concatenate((breaks, [where.size])) - 1
        ids, run_of = np.unique(values[starts], return_inverse=True)
        counts = np.zeros(ids.size, dtype=np.int64)
        np.add.at(counts, run_of, ends - starts + 1)
        boxes = np.empty((ids.size, 4), dtype=np.int64)
        boxes[:, 0], boxes[:, 1] = height, -1
        boxes[:, 2], boxes[:, 3] = width, -1
        np.minimum.at(boxes[:, 0], run_of, rows[starts])
        np.maximum.at(boxes[:, 1], run_of, rows[starts])
        np.minimum.at(boxes[:, 2], run_of, cols[starts])
        np.maximum.at(boxes[:, 3], run_of, cols[ends])
        boxes[:, 1] += 1
        boxes[:, 3] += 1
        return cls(ids.astype(np.int64), counts, boxes)

    def box(self, instance_id: int) -> tuple[int, int, int, int] | None:
        """Half-open (row0, row1, col0, col1) of one id, or None when no pixel carries it."""
        at = int(np.searchsorted(self.ids, instance_id))
        if at >= self.ids.size or self.ids[at] != instance_id:
            return None
        return tuple(int(v) for v in self.boxes[at])  # type: ignore[return-value]


@dataclass(frozen=True)
class BranchMasks:
    """Branch instances of one frame.

    `labels` is an `H×W` `int32` image (0 background, `trunk_id` the trunk when not None, values
    in `ignored_ids` neither branch nor trunk, any other value one branch); `source` says where the
    instances came from (e.g. a file name, "geometric"); `scores` maps a branch id to the
    segmenter's belief (0..1) that it is a branch (absent = 1: a mask file is taken as true), and
    `calibration` maps the resulting cut-point confidence to a measured share correct. `light` is the
    frame's measured light when the segmenter read its confidences by it, and `target_min_confidence` the
    least confidence a target needs in that light by its calibration, beyond the settings' own (0: none
    beyond them; `math.inf`: no confidence in that light was reliable enough for a target).
    `visible_length_scale_m` (> 0): a cut point's confidence is also scaled by how long its branch is seen
    (`visible_length_factor`), as the segmenter's calibration was measured with it; 0: not. `ood`: the learned
    segmenter's reading of whether its model knows the frame (`segmentation.ood`), None without one. The
    ids, sizes and bounding boxes are indexed once, on first use (`index`): treat `labels` as
    read-only after that.
    """

    labels: np.ndarray
    trunk_id: int | None = None
    source: str = "array"
    ignored_ids: tuple[int, ...] = ()
    scores: dict[int, float] = field(default_factory=dict)
    calibration: ConfidenceCalibration | None = None
    light: LightReading | None = None
    target_min_confidence: float = 0.0
    visible_length_scale_m: float = 0.0
    ood: OodReading | None = None

    def reported_confidence(self, branch_id: int) -> Callable[[float, float], float] | None:
        """How a cut point's own confidence and its branch's visible length (m) become the reported confidence
        for instance `branch_id`: scaled by the segmenter's score and by `visible_length_factor`, then through its
        `calibration`; None when none applies (a mask file)."""
        score, calibration, scale_m = self.scores.get(branch_id, 1.0), self.calibration, self.visible_length_scale_m
        if score == 1.0 and calibration is None and scale_m == 0:
            return None

        def reported(raw: float, visible_m: float) -> float:
            scaled = score * raw * visible_length_factor(visible_m, scale_m)
            return scaled if calibration is None else calibration(scaled)

        return reported

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the mask in pixels."""
        return self.labels.shape

    @cached_property
    def index(self) -> InstanceIndex:
        """Ids, pixel counts and bounding boxes of every instance (one pass over the labels)."""
        return InstanceIndex.of(self.labels)

    def branch_ids(self) -> list[int]:
        """Ids of the branch instances present, ascending (background and trunk excluded)."""
        skip = set(self.ignored_ids) | ({self.trunk_id} if self.trunk_id is not None else set())
        return [int(i) for i in self.index.ids if int(i) not in skip]

    def crop(self, instance_id: int, margin: int = 2) -> MaskCrop | None:
        """One instance as a `MaskCrop`: its bounding box grown by `margin` px; None when absent."""
        box = self.index.box(instance_id)
        if box is None:
            return None
        r0, r1, c0, c1 = _grown(box, margin, self.shape)
        return MaskCrop(self.labels[r0:r1, c0:c1] == instance_id, r0, c0, self.shape)

    def branch(self, branch_id: int) -> np.ndarray:
        """Boolean `H×W` mask of one branch instance."""
        crop = self.crop(branch_id, margin=0)
        return crop.full() if crop is not None else np.zeros(self.shape, dtype=bool)

    def trunk_crop(self, margin: int = 2) -> MaskCrop | None:
        """The trunk as a `MaskCrop`, or None when no trunk id is set or no pixel carries it."""
        return None if self.trunk_id is None else self.crop(self.trunk_id, margin)

    def trunk(self) -> np.ndarray | None:
        """Boolean `H×W` trunk mask, or None when no trunk id is set or no pixel carries it."""
        crop = self.trunk_crop(margin=0)
        return None if crop is None else crop.full()


def check_instance_count(masks: BranchMasks, max_instances: int) -> None:
    """Raise `MaskError` naming the count and the cap when `masks` holds more than `max_instances`
    branch instances (`cutpoints.max_instances`): O(pixels) once, so a caller can refuse such a
    mask before any other work (`estimate_cut_points` checks it first thing)."""
    count = len(masks.branch_ids())
    if count > max_instances:
        raise MaskError(
            f"{masks.source}: the mask holds {count} branch instances, more than "
            f"cutpoints.max_instances = {max_instances}; a frame of branches has tens, "
            "not thousands (is it a label image of another kind?)"
        )


def split_binary(mask: np.ndarray, min_area_px: int = 1) -> np.ndarray:
    """Instance labels (`int32` `H×W`, 1..K) of the 8-connected components of a binary `H×W` mask.

    Components smaller than `min_area_px` pixels are dropped (label 0): speckle is not a branch.
    """
    binary = (np.asarray(mask) != 0).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    kept = stats[:, cv2.CC_STAT_AREA] >= min_area_px
    kept[0] = False  # the background
    keep = np.where(kept, np.cumsum(kept), 0).astype(np.int32)
    return keep[labels]


def _looks_binary(array: np.ndarray, trunk_id: int | None) -> bool:
    """A mask whose only non-zero value is 255 (or True) and is not the trunk id reads as binary."""
    if trunk_id == 255 or not array.size or int(array.max()) != 255:
        return False
    return bool(np.count_nonzero(array == 255) == np.count_nonzero(array))


def masks_from_array(
    mask: np.ndarray,
    *,
    trunk_id: int | None = DEFAULT_TRUNK_ID,
    kind: MaskKind = "auto",
    source: str = "array",
    ignored_ids: tuple[int, ...] = DEFAULT_IGNORED_IDS,
) -> BranchMasks:
    """`BranchMasks` from an `H×W` integer or boolean array.

    `kind="instance"` keeps ids as they are (`ignored_ids` are neither branch nor trunk);
    `"binary"` splits non-zero pixels into connected
    components (no trunk); `"auto"` treats boolean arrays and 8-bit masks holding only 0/255 as
    binary and everything else as instance ids.
    """
    array = np.asarray(mask)
    if array.ndim == 3 and array.shape[2] in (3, 4) and np.all(array[..., :3] == array[..., :1]):
        array = array[..., 0]  # a grey mask saved as RGB(A)
    if array.ndim != 2:
        raise MaskError(f"{source}: a mask must be a single-channel H×W image, got shape {array.shape}")
    if array.dtype == bool:
        array = array.astype(np.uint8) * 255
        if kind == "auto":
            kind = "binary"
    if not np.issubdtype(array.dtype, np.integer):
        if not np.all(np.isfinite(array)) or np.any(array != np.round(array)):
            raise MaskError(f"{source}: mask values must be whole numbers (instance ids), got dtype {array.dtype}")
        array = array.astype(np.int64)
    if array.size and array.min() < 0:
        raise MaskError(f"{source}: mask ids must be ≥ 0, found {int(array.min())}")
    if array.size and array.max() > np.iinfo(np.int32).max:
        raise MaskError(f"{source}: mask id {int(array.max())} is out of range")
    if kind == "auto":
        kind = "binary" if _looks_binary(array, trunk_id) else "instance"
    if kind == "binary":
        return BranchMasks(split_binary(array), None, source)
    if kind != "instance":
        raise MaskError(f"{source}: mask kind {kind!r} is not one of 'auto', 'instance', 'binary'")
    return BranchMasks(array.astype(np.int32), trunk_id, source, tuple(ignored_ids))


def read_mask(
    path: str | Path,
    *,
    trunk_id: int | None = DEFAULT_TRUNK_ID,
    kind: MaskKind = "auto",
    ignored_ids: tuple[int, ...] = DEFAULT_IGNORED_IDS,
) -> BranchMasks:
    """Read an instance-id PNG (8- or 16-bit) or a binary mask image into `BranchMasks`."""
    path = Path(path)
    if not path.is_file():
        raise MaskError(f"mask file {path} does not exist")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise MaskError(f"mask file {path} could not be decoded as an image (expected an 8- or 16-bit PNG)")
    if image.dtype not in (np.uint8, np.uint16):
        raise MaskError(f"mask file {path} has pixel type {image.dtype}; expected 8- or 16-bit integers")
    return masks_from_array(image, trunk_id=trunk_id, kind=kind, source=str(path), ignored_ids=ignored_ids)


def write_instance_mask(path: str | Path, masks: BranchMasks | np.ndarray) -> Path:
    """Write instance ids as a PNG: 8-bit when every id fits, else 16-bit. Returns the path."""
    labels = masks.labels if isinstance(masks, BranchMasks) else np.asarray(masks)
    if labels.size and (labels.min() < 0 or labels.max() > 65535):
        raise MaskError(f"{path}: instance ids must be in 0..65535 to fit a PNG")
    dtype = np.uint8 if (labels.size == 0 or labels.max() <= 255) else np.uint16
    path = Path(path)
    if not cv2.imwrite(str(path), labels.astype(dtype)):
        raise MaskError(f"could not write mask {path}")
    return path


def validate_masks(masks: BranchMasks, image_shape: tuple[int, ...]) -> None:
    """Raise `MaskError` unless the mask matches the image's `(H, W)` pixel for pixel.

    A mask without any branch is not an error here: the pipeline reports it as an empty result with
    a reason, since "no branch in view" is a normal answer.
    """
    expected = tuple(image_shape[:2])
    if masks.shape != expected:
        raise MaskError(
            f"{masks.source}: mask is {masks.shape[1]}×{masks.shape[0]} (W×H) but the images are "
            f"{expected[1]}×{expected[0]}; the mask must match the left image pixel for pixel"
        )


def erode(mask: np.ndarray, pixels: int, keep_fraction: float = 0.3) -> np.ndarray:
    """Boolean `H×W` mask shrunk by `pixels` (3×3 cross steps), or the mask itself when erosion
    would keep less than `keep_fraction` of it (a branch only a few pixels wide).

    Why: stereo depth at a silhouette mixes the branch and what lies behind it; one or two pixels
    inward the disparity belongs to the branch — unless there is no inward.
    """
    mask = mask.astype(bool)
    if pixels <= 0:
        return mask
    kernel = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    eroded = cv2.erode(mask.astype(np.uint8), kernel, iterations=pixels).astype(bool)
    return eroded if eroded.sum() >= keep_fraction * mask.sum() else mask


#: `masks.kind`: how a mask file or array is read (`branchrange.core.masks.masks_from_array`).
MASK_KINDS: tuple[str, ...] = ("auto", "instance", "binary")


@dataclass(frozen=True)
class MaskConfig(Settings):
    """How instance masks (files, arrays, recordings' masks) are read (`branchrange.core.masks.masks_from_array`).

    `trunk_id`: the trunk's id in instance masks (1..65535); `ignored_ids`: ids that are neither
    branch nor trunk (twigs, leaves); `kind`: 'auto' (binary when the mask holds only 0 and one
    value), 'instance' or 'binary' (connected components are the instances).
    """

    section = "masks"
    error = ConfigError
    limits = {
        "trunk_id": Limit(minimum=1, maximum=65535),
        "ignored_ids": Limit(minimum=1, maximum=65535),
        "kind": Limit(enum=MASK_KINDS, expected=one_of(MASK_KINDS)),
    }

    trunk_id: int = DEFAULT_TRUNK_ID
    ignored_ids: tuple[int, ...] = DEFAULT_IGNORED_IDS
    kind: str = "auto"

    def checks(self) -> Checks:
        """The rules beyond each key's `Limit`."""
        return {
            "trunk_id": (0 < self.trunk_id <= 65535, "an id in 1..65535 (0 is background)"),
            "ignored_ids": (all(0 < i <= 65535 for i in self.ignored_ids), "ids in 1..65535"),
        }
