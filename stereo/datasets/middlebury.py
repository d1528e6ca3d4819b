"""Middlebury stereo: the 2014/2021 layout (PFM) and the 2001 layout (scaled 8-bit PNG).

One folder per scene under the root, either

- `im0.png`, `im1.png`, `disp0.pfm` or `disp0GT.pfm` (pixels, inf = unknown), or
- `imL.png`, `imR.png`, `groundtruth.png` with `info.txt` giving the grey-level scale (2001).

Images are used at the resolution on disk. Disparities ≥ `max_disp` (192 by default, as the
authors' tools) are masked out.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stereo.datasets.base import DatasetError, PairRecord, StereoDataset, require_dir
from stereo.io import read_middlebury2001_disparity, read_middlebury2001_info, read_pfm


def _scene_record(scene: Path) -> PairRecord | None:
    """The pair of one scene folder in either layout, or None when the folder holds neither."""
    for disp_name in ("disp0.pfm", "disp0GT.pfm"):
        if (scene / "im0.png").is_file() and (scene / "im1.png").is_file() and (scene / disp_name).is_file():
            return PairRecord(scene / "im0.png", scene / "im1.png", scene / disp_name, name=scene.name)
    if all((scene / f).is_file() for f in ("imL.png", "imR.png", "groundtruth.png", "info.txt")):
        return PairRecord(scene / "imL.png", scene / "imR.png", scene / "groundtruth.png", name=scene.name)
    return None


class MiddleburyDataset(StereoDataset):
    """Middlebury scenes found directly under `root` (or `root` itself when it is one scene)."""

    name = "middlebury"

    def __init__(self, root: str | Path, *, max_disp: float | None = 192.0) -> None:
        self.root = require_dir(Path(root), "Middlebury scene folders")
        scenes = [self.root] + sorted(p for p in self.root.iterdir() if p.is_dir())
        records = [r for r in (_scene_record(s) for s in scenes) if r is not None]
        if not records:
            raise DatasetError(
                f"{self.root}: no Middlebury scene found; expected <scene>/im0.png, im1.png, disp0[GT].pfm "
                "or <scene>/imL.png, imR.png, groundtruth.png, info.txt"
            )
        super().__init__(records, max_disp=max_disp)

    def read_ground_truth(self, record: PairRecord) -> np.ndarray:
        """Disparity from the PFM, or from the 2001 PNG divided by its `info.txt` scale (0 = unknown)."""
        gt = record.ground_truth
        if gt.suffix == ".pfm":
            return read_pfm(gt)
        info = read_middlebury2001_info(gt.parent / "info.txt")
        return read_middlebury2001_disparity(gt, info.scale)
