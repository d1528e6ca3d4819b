"""SceneFlow (FlyingThings3D, Monkaa, Driving) in the layout of the authors' open-dataset tools.

Under the root, each subset has a frames folder and a disparity folder that mirror each other::

    flyingthings3d__frames/<A|B|C>/<seq>/{left,right}/NNNN.png   flyingthings3d_disparity/<A|B|C>/<seq>/left/NNNN.pfm
    monkaa__frames/<scene>/{left,right}/NNNN.png                  monkaa_disparity/<scene>/left/NNNN.pfm
    driving__frames/<focal>/<dir>/<speed>/{left,right}/NNNN.png   driving__disparity/<focal>/<dir>/<speed>/left/NNNN.pfm

Only the left disparity (PFM, pixels) is used. Subsets whose folders are absent are skipped.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from stereo.datasets.base import DatasetError, PairRecord, StereoDataset, require_dir
from stereo.io import read_pfm

#: subset name → (frames folder, disparity folder), relative to the SceneFlow root.
SCENEFLOW_SUBSETS: dict[str, tuple[str, str]] = {
    "flyingthings3d": ("flyingthings3d__frames", "flyingthings3d_disparity"),
    "monkaa": ("monkaa__frames", "monkaa_disparity"),
    "driving": ("driving__frames", "driving__disparity"),
}


def _subset_records(frames: Path, disparities: Path, subset: str) -> list[PairRecord]:
    """Every left frame under `frames` that has a right frame and a left disparity PFM."""
    records = []
    for left_dir in sorted(p for p in frames.rglob("left") if p.is_dir()):
        sequence = left_dir.parent.relative_to(frames)
        right_dir = left_dir.parent / "right"
        disp_dir = disparities / sequence / "left"
        for left in sorted(left_dir.glob("*.png")):
            right, disp = right_dir / left.name, disp_dir / f"{left.stem}.pfm"
            if right.is_file() and disp.is_file():
                records.append(PairRecord(left, right, disp, name=f"{subset}/{sequence.as_posix()}/{left.stem}"))
    return records


class SceneFlowDataset(StereoDataset):
    """SceneFlow pairs of the chosen subsets (all three by default), in subset then path order."""

    name = "sceneflow"

    def __init__(
        self,
        root: str | Path,
        subsets: Mapping[str, tuple[str, str]] | None = None,
        *,
        max_disp: float | None = None,
    ) -> None:
        self.root = require_dir(
            Path(root), "a SceneFlow root holding <subset>__frames/ and <subset>_disparity/ folders"
        )
        table = SCENEFLOW_SUBSETS if subsets is None else dict(subsets)
        records: list[PairRecord] = []
        for subset, (frames_name, disp_name) in table.items():
            frames, disparities = self.root / frames_name, self.root / disp_name
            if frames.is_dir() and disparities.is_dir():
                records.extend(_subset_records(frames, disparities, subset))
        if not records:
            expected = ", ".join(f"{f}/ + {d}/" for f, d in table.values())
            raise DatasetError(f"{self.root}: no SceneFlow pairs found; expected one of {expected}")
        super().__init__(records, max_disp=max_disp)

    def read_ground_truth(self, record: PairRecord) -> np.ndarray:
        """Left disparity from the PFM (channel 0 when stored in colour)."""
        return read_pfm(record.ground_truth)
