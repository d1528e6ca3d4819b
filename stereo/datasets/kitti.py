"""KITTI 2012 / 2015 stereo in the re-organised layout of the authors' tools.

Under the root: `left/`, `right/` and `ground_truth/` holding the same `*.png` file names; the
ground truth is a uint16 PNG of disparity × 256, 0 = invalid.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stereo.datasets.base import DatasetError, PairRecord, StereoDataset, require_dir
from stereo.io import read_kitti_disparity


class KittiDataset(StereoDataset):
    """KITTI pairs (`year` 2012 or 2015 only names the dataset; the layout is the same)."""

    def __init__(self, root: str | Path, year: int = 2015, *, max_disp: float | None = None) -> None:
        if year not in (2012, 2015):
            raise DatasetError(f"KITTI year {year!r}: expected 2012 or 2015")
        self.name = f"kitti{year}"
        self.root = Path(root)
        left_dir = require_dir(self.root / "left", "KITTI left images (*.png)")
        right_dir = require_dir(self.root / "right", "KITTI right images with the left images' names")
        gt_dir = require_dir(self.root / "ground_truth", "KITTI uint16 disparity PNGs with the left images' names")
        records = [
            PairRecord(left, right_dir / left.name, gt_dir / left.name, name=left.stem)
            for left in sorted(left_dir.glob("*.png"))
            if (right_dir / left.name).is_file() and (gt_dir / left.name).is_file()
        ]
        if not records:
            raise DatasetError(f"{self.root}: no pair has all of left/NAME.png, right/NAME.png, ground_truth/NAME.png")
        super().__init__(records, max_disp=max_disp)

    def read_ground_truth(self, record: PairRecord) -> np.ndarray:
        """Disparity from the uint16 PNG (value / 256, 0 = invalid)."""
        return read_kitti_disparity(record.ground_truth)
