"""Stereo datasets: one template (`base`) and one module per dataset, plus splits and transforms."""

from __future__ import annotations

from pathlib import Path

from stereo.datasets.base import DatasetError, PairRecord, StereoDataset
from stereo.datasets.eth3d import Eth3dDataset
from stereo.datasets.kitti import KittiDataset
from stereo.datasets.middlebury import MiddleburyDataset
from stereo.datasets.sceneflow import SceneFlowDataset
from stereo.datasets.synthetic import SyntheticDataset
from stereo.datasets.unlabelled import RectifiedPairsDataset
from stereo.datasets.virtualtree import VirtualTreeDataset

#: Datasets that come with split files; the others are split 90/10 (seed 0) or by group.
SPLIT_FILE_DATASETS = ("virtualtree", "synthetic")


def open_dataset(name: str, root: str | Path, split: str | Path | None = None) -> StereoDataset:
    """Open dataset `name` at `root`; `split` (a split-file name or path) only for VirtualTree-layout sets."""
    if split is not None and name not in SPLIT_FILE_DATASETS:
        raise DatasetError(f"dataset {name!r} has no split files (split {str(split)!r}); use the 90/10 or group split")
    if name == "virtualtree":
        return VirtualTreeDataset(root, split)
    if name == "synthetic":
        return SyntheticDataset(root, split)
    if name == "sceneflow":
        return SceneFlowDataset(root)
    if name in ("kitti2012", "kitti2015"):
        return KittiDataset(root, year=int(name[-4:]))
    if name == "eth3d":
        return Eth3dDataset(root)
    if name == "middlebury":
        return MiddleburyDataset(root)
    raise DatasetError(
        f"unknown dataset {name!r}; expected virtualtree, synthetic, sceneflow, kitti2012, kitti2015, "
        "eth3d or middlebury"
    )


__all__ = [
    "DatasetError",
    "Eth3dDataset",
    "KittiDataset",
    "MiddleburyDataset",
    "PairRecord",
    "SceneFlowDataset",
    "RectifiedPairsDataset",
    "StereoDataset",
    "SyntheticDataset",
    "VirtualTreeDataset",
    "open_dataset",
]
