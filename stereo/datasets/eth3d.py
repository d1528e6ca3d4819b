"""ETH3D two-view training set.

Images: `two_view_training/<scene>/im0.png` (left) and `im1.png` (right); ground truth:
`two_view_training_disparity/<scene>/disp0GT.pfm` (pixels, inf = unknown).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stereo.datasets.base import DatasetError, PairRecord, StereoDataset, require_dir
from stereo.io import read_pfm


class Eth3dDataset(StereoDataset):
    """ETH3D two-view scenes that have both images and a `disp0GT.pfm`."""

    name = "eth3d"

    def __init__(self, root: str | Path, *, max_disp: float | None = None) -> None:
        self.root = Path(root)
        images = require_dir(self.root / "two_view_training", "ETH3D scenes <scene>/im0.png, im1.png")
        disparities = require_dir(self.root / "two_view_training_disparity", "ETH3D <scene>/disp0GT.pfm")
        records = []
        for scene in sorted(p for p in images.iterdir() if p.is_dir()):
            left, right, disp = scene / "im0.png", scene / "im1.png", disparities / scene.name / "disp0GT.pfm"
            if left.is_file() and right.is_file() and disp.is_file():
                records.append(PairRecord(left, right, disp, name=scene.name))
        if not records:
            raise DatasetError(f"{images}: no scene has im0.png, im1.png and a matching disp0GT.pfm")
        super().__init__(records, max_disp=max_disp)

    def read_ground_truth(self, record: PairRecord) -> np.ndarray:
        """Disparity from the PFM."""
        return read_pfm(record.ground_truth)
