"""Branch instance masks: read instance-id PNGs or binary masks, split into instances, validate.

An instance mask is an `H×W` integer image: 0 = background, one id per branch, and optionally one
id (the trunk id, configurable) for the trunk. A binary mask (any non-zero = branch) is split into
its 8-connected components, each one branch; a binary mask knows no trunk.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

#: The trunk's id in instance masks unless configured otherwise (the synthetic generator's value).
DEFAULT_TRUNK_ID = 65535
#: Ids that are neither branch nor trunk unless configured otherwise: the top of the 16-bit range
#: is reserved for twigs (65534) and leaves (65533), as the synthetic generator writes them.
DEFAULT_IGNORED_IDS: tuple[int, ...] = (65533, 65534)

MaskKind = Literal["auto", "instance", "binary"]


class MaskError(ValueError):
    """A mask that cannot be used: unreadable, wrong size, wrong type, or holding no branch."""


@dataclass(frozen=True)
class BranchMasks:
    """Branch instances of one frame.

    `labels` is an `H×W` `int32` image (0 background, `trunk_id` the trunk when not None, values
    in `ignored_ids` neither branch nor trunk, any other value one branch); `source` says where the
    instances came from (e.g. a file name, "geometric").
    """

    labels: np.ndarray
    trunk_id: int | None = None
    source: str = "array"
    ignored_ids: tuple[int, ...] = ()

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the mask in pixels."""
        return self.labels.shape  # type: ignore[return-value]

    def branch_ids(self) -> list[int]:
        """Ids of the branch instances present, ascending (background and trunk excluded)."""
        ids = np.unique(self.labels)
        return [int(i) for i in ids if i != 0 and i != self.trunk_id and i not in self.ignored_ids]

    def branch(self, branch_id: int) -> np.ndarray:
        """Boolean `H×W` mask of one branch instance."""
        return self.labels == branch_id

    def trunk(self) -> np.ndarray | None:
        """Boolean `H×W` trunk mask, or None when no trunk id is set or no pixel carries it."""
        if self.trunk_id is None:
            return None
        trunk = self.labels == self.trunk_id
        return trunk if trunk.any() else None


def split_binary(mask: np.ndarray, min_area_px: int = 1) -> np.ndarray:
    """Instance labels (`int32` `H×W`, 1..K) of the 8-connected components of a binary `H×W` mask.

    Components smaller than `min_area_px` pixels are dropped (label 0): speckle is not a branch.
    """
    binary = (np.asarray(mask) != 0).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    keep = np.zeros(count, dtype=np.int32)
    next_id = 1
    for label in range(1, count):
        if stats[label, cv2.CC_STAT_AREA] >= min_area_px:
            keep[label] = next_id
            next_id += 1
    return keep[labels]


def _looks_binary(values: np.ndarray, trunk_id: int | None) -> bool:
    """A mask whose only non-zero value is 255 (or True) and is not the trunk id reads as binary."""
    nonzero = values[values != 0]
    return len(nonzero) == 1 and int(nonzero[0]) == 255 and trunk_id != 255


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
        kind = "binary" if _looks_binary(np.unique(array), trunk_id) else "instance"
    if kind == "binary":
        return BranchMasks(split_binary(array), None, source)
    if kind != "instance":
        raise MaskError(f"{source}: mask kind {kind!r} is not one of 'auto', 'instance', 'binary'")
    return BranchMasks(array.astype(np.int32), trunk_id, source, tuple(ignored_ids))


def read_mask(path: str | Path, *, trunk_id: int | None = DEFAULT_TRUNK_ID, kind: MaskKind = "auto",
              ignored_ids: tuple[int, ...] = DEFAULT_IGNORED_IDS) -> BranchMasks:
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
