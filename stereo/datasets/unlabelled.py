"""Unlabelled rectified pairs — e.g. a team's own ZED recordings — for self-supervised fine-tuning.

Layout: `left/NAME.png` and `right/NAME.png` (any of .png, .jpg, .jpeg) with matching names. The
pairs must already be rectified (rows aligned). Samples carry an all-zero disparity (= unknown).
"""

from __future__ import annotations

from pathlib import Path

from stereo.datasets.base import DatasetError, PairRecord, StereoDataset, require_dir

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


class RectifiedPairsDataset(StereoDataset):
    """Pairs `left/NAME` + `right/NAME` without ground truth."""

    name = "unlabelled"

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        left_dir = require_dir(self.root / "left", "rectified left images (left/NAME.png)")
        right_dir = require_dir(self.root / "right", "rectified right images with the left images' names")
        records = [
            PairRecord(left, right_dir / left.name, None, name=left.stem)
            for left in sorted(left_dir.iterdir())
            if left.suffix.lower() in IMAGE_SUFFIXES and (right_dir / left.name).is_file()
        ]
        if not records:
            raise DatasetError(f"{self.root}: no image in left/ has a right/ image of the same name")
        super().__init__(records)
