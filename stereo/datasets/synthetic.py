"""Synthetic scenes written by `emcstereo synth` (`stereo.synth.write_dataset`).

They use the VirtualTree layout (left/right PNGs, EXR depth in centimetres, split files), but at
their own image size, so the rig that turns depth into disparity — focal length in pixels at the
written width and baseline — is read from the `synth.json` the writer leaves in the root
(`camera.focal_px`, `camera.baseline_m`).
"""

from __future__ import annotations

import json
from pathlib import Path

from stereo.datasets.base import DatasetError
from stereo.datasets.virtualtree import VirtualTreeDataset

META_FILE = "synth.json"


def read_rig(root: Path) -> tuple[float, float]:
    """(focal_px, baseline_cm) of a synthetic set, from its `synth.json`."""
    path = root / META_FILE
    try:
        camera = json.loads(path.read_text(encoding="utf-8"))["camera"]
        focal_px, baseline_m = float(camera["focal_px"]), float(camera["baseline_m"])
    except FileNotFoundError as exc:
        raise DatasetError(
            f"{path}: not found; a synthetic set carries its rig there (camera.focal_px, camera.baseline_m)"
        ) from exc
    except (ValueError, KeyError, TypeError) as exc:
        raise DatasetError(
            f"{path}: expected JSON with a camera object holding numeric focal_px and baseline_m ({exc})"
        ) from exc
    if focal_px <= 0 or baseline_m <= 0:
        raise DatasetError(f"{path}: focal_px {focal_px} and baseline_m {baseline_m} must be positive")
    return focal_px, baseline_m * 100.0


class SyntheticDataset(VirtualTreeDataset):
    """A synthetic set: VirtualTree layout with the rig of its `synth.json`."""

    name = "synthetic"

    def __init__(self, root: str | Path, split: str | Path | None = None, *, max_disp: float | None = None) -> None:
        focal_px, baseline_cm = read_rig(Path(root))
        super().__init__(root, split, focal_px=focal_px, baseline_cm=baseline_cm, max_disp=max_disp)
