"""KITTI 2012/2015 disparity PNGs: 16-bit grey, disparity = value / 256, value 0 = no ground truth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from stereo.io.errors import ArrayFormatError, MalformedFileError

KITTI_SCALE = 256.0
KITTI_MAX_DISPARITY = np.iinfo(np.uint16).max / KITTI_SCALE


def read_kitti_disparity(path: str | Path) -> np.ndarray:
    """Read a KITTI disparity PNG as float32 `H×W` pixels; pixels without ground truth are 0."""
    path = Path(path)
    data = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    raw = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if raw is None:
        raise MalformedFileError(f"{path}: not a readable PNG, expected a KITTI 16-bit disparity image")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        channels = 1 if raw.ndim == 2 else raw.shape[2]
        raise MalformedFileError(
            f"{path}: a KITTI disparity PNG is 16-bit single-channel, found {raw.dtype} with {channels} channel(s)"
        )
    return raw.astype(np.float32) / np.float32(KITTI_SCALE)


def write_kitti_disparity(path: str | Path, disparity: np.ndarray) -> None:
    """Write float `H×W` disparity (pixels) as a KITTI PNG.

    Non-finite and non-positive values become 0 (invalid). A valid disparity below 1/256 px is stored
    as 1/256 so that it stays valid; a disparity above 65535/256 ≈ 256 px cannot be stored and raises.
    """
    path = Path(path)
    disparity = np.asarray(disparity)
    if disparity.ndim != 2 or not np.issubdtype(disparity.dtype, np.number):
        raise ArrayFormatError(
            f"cannot write {path}: expected a numeric H×W disparity, got {disparity.dtype} {disparity.shape}"
        )
    disparity = disparity.astype(np.float64)
    valid = np.isfinite(disparity) & (disparity > 0)
    too_far = valid & (disparity > KITTI_MAX_DISPARITY)
    if too_far.any():
        raise ArrayFormatError(
            f"cannot write {path}: {int(too_far.sum())} disparities exceed the KITTI maximum "
            f"{KITTI_MAX_DISPARITY:.3f} px (largest {disparity[too_far].max():.3f})"
        )
    raw = np.zeros(disparity.shape, dtype=np.uint16)
    raw[valid] = np.clip(np.rint(disparity[valid] * KITTI_SCALE), 1, np.iinfo(np.uint16).max).astype(np.uint16)
    ok, encoded = cv2.imencode(".png", raw)
    if not ok:
        raise ArrayFormatError(f"cannot write {path}: OpenCV failed to encode the 16-bit PNG")
    path.write_bytes(encoded.tobytes())
