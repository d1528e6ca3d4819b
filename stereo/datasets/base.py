"""The dataset template every stereo dataset follows: a list of pair records and how to read them.

A dataset is a `torch.utils.data.Dataset` of *raw* samples — dicts with

- `left`, `right`: RGB `uint8` `H×W×3` arrays (the project's image convention),
- `disparity`: `float32` `H×W` pixels, left reference, 0 where invalid or unknown,
- `meta`: `{"dataset": str, "name": str, "index": int}`.

Each concrete dataset only discovers its records and reads its own disparity format; training
transforms (crop, jitter, normalisation) are applied by `stereo.datasets.transforms.Augmented`.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from torch.utils.data import Dataset

from stereo.io import read_rgb


class DatasetError(ValueError):
    """A dataset folder, split file or record is missing or not in the expected layout."""


@dataclass(frozen=True)
class PairRecord:
    """One rectified stereo pair on disk: image paths, ground-truth path (None when unlabelled), a name."""

    left: Path
    right: Path
    ground_truth: Path | None
    name: str


def sanitize_disparity(disparity: np.ndarray) -> np.ndarray:
    """Return `float32` `H×W` disparity (px) with NaN, ±Inf and negative values set to 0 (= invalid)."""
    out = np.array(disparity, dtype=np.float32, copy=True)
    out[~np.isfinite(out) | (out < 0)] = 0.0
    return out


def crop_to_common_size(*arrays: np.ndarray) -> list[np.ndarray]:
    """Crop arrays to their common top-left `min(H) × min(W)` (some open datasets differ by a pixel)."""
    height = min(a.shape[0] for a in arrays)
    width = min(a.shape[1] for a in arrays)
    return [np.ascontiguousarray(a[:height, :width]) for a in arrays]


def require_dir(path: Path, what: str) -> Path:
    """Return `path` if it is a directory, else raise DatasetError naming it and what it should hold."""
    if not path.is_dir():
        raise DatasetError(f"{path}: folder not found; expected {what}")
    return path


class StereoDataset(Dataset):
    """Template of a labelled (or unlabelled) stereo dataset: records plus a ground-truth reader.

    Subclasses find their records in `__init__` and implement `read_ground_truth(record)`.
    `max_disp`, when given, additionally marks disparities `>= max_disp` invalid (Middlebury's rule).
    """

    #: Short dataset name written into every sample's `meta`.
    name: str = "stereo"

    def __init__(self, records: Sequence[PairRecord], *, max_disp: float | None = None) -> None:
        self.records: list[PairRecord] = list(records)
        self.max_disp = max_disp

    def __len__(self) -> int:
        return len(self.records)

    def read_ground_truth(self, record: PairRecord) -> np.ndarray:
        """Disparity in pixels, `float32` `H×W`, of `record` as stored (before sanitising)."""
        raise NotImplementedError(f"{type(self).__name__} does not say how to read its ground truth")

    def load(self, index: int) -> dict[str, Any]:
        """The raw sample `index` (uint8 RGB images, sanitised float32 disparity, meta)."""
        if not 0 <= index < len(self.records):
            raise IndexError(f"{self.name}: sample {index} out of range 0..{len(self.records) - 1}")
        record = self.records[index]
        left, right = read_rgb(record.left), read_rgb(record.right)
        if record.ground_truth is None:
            disparity = np.zeros(left.shape[:2], dtype=np.float32)
        else:
            disparity = sanitize_disparity(self.read_ground_truth(record))
            if self.max_disp is not None:
                disparity[disparity >= self.max_disp] = 0.0
        left, right, disparity = crop_to_common_size(left, right, disparity)
        return {
            "left": left,
            "right": right,
            "disparity": disparity,
            "meta": {"dataset": self.name, "name": record.name, "index": index},
        }

    def __getitem__(self, index: int) -> dict[str, Any]:
        return self.load(index)

    def subset(self, indices: Sequence[int]) -> StereoDataset:
        """A dataset of the same kind holding only `indices`, in the order given."""
        part = copy.copy(self)
        part.records = [self.records[i] for i in indices]
        return part

    def names(self) -> list[str]:
        """The record names, in order (split files and group patterns match against these)."""
        return [r.name for r in self.records]
