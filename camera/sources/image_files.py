"""RGB image files through OpenCV (which speaks BGR): the only place the sources convert colour order."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from camera.sources.atomic_file import replace_atomically
from camera.sources.frame import CorruptFrameError


def read_rgb(path: Path) -> np.ndarray:
    """An H×W×3 uint8 RGB image from a file; CorruptFrameError when it is missing or cannot be decoded."""
    data = np.fromfile(str(path), dtype=np.uint8) if path.is_file() else None
    if data is None:
        raise CorruptFrameError(f"{path}: image file is missing; expected the frame listed in the recording")
    image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if image is None:
        raise CorruptFrameError(f"{path}: cannot be decoded as an image ({data.size} bytes); expected a PNG/JPEG frame")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def write_rgb(path: Path, image: np.ndarray) -> None:
    """Write an H×W×3 uint8 RGB image, atomically; the format follows the suffix (PNG lossless, JPEG quality 95)."""
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1] if path.suffix.lower() == ".png" else [cv2.IMWRITE_JPEG_QUALITY, 95]
    ok, encoded = cv2.imencode(path.suffix, cv2.cvtColor(image, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise OSError(f"{path}: OpenCV could not encode a {image.shape} image as {path.suffix}")
    replace_atomically(path, encoded.data)


def read_mask(path: Path) -> np.ndarray:
    """An H×W uint8/uint16 mask (instance ids) from a PNG, unchanged; CorruptFrameError when unreadable."""
    data = np.fromfile(str(path), dtype=np.uint8) if path.is_file() else None
    mask = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data is not None and data.size else None
    if mask is None or mask.ndim != 2:
        found = "missing" if data is None else f"not a single-channel image ({data.size} bytes)"
        raise CorruptFrameError(f"{path}: mask is {found}; expected the 8/16-bit PNG listed in the recording")
    return mask


def write_mask(path: Path, mask: np.ndarray) -> None:
    """Write an H×W uint8/uint16 mask (instance ids) as a lossless PNG, atomically."""
    if mask.ndim != 2 or mask.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{path}: mask is {mask.dtype} of shape {mask.shape}; expected uint8 or uint16 H×W")
    ok, encoded = cv2.imencode(".png", mask)
    if not ok:
        raise OSError(f"{path}: OpenCV could not encode a {mask.shape} mask as PNG")
    replace_atomically(path, encoded.data)


def split_side_by_side(bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) RGB halves of a side-by-side BGR frame (H×2W×3), as ZED cameras and SBS videos deliver."""
    if bgr is None or bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.shape[1] % 2:
        shape = None if bgr is None else bgr.shape
        raise CorruptFrameError(f"side-by-side frame has shape {shape}; expected H×2W×3 with an even width")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    half = rgb.shape[1] // 2
    return np.ascontiguousarray(rgb[:, :half]), np.ascontiguousarray(rgb[:, half:])
