"""Reading and writing 8-bit images as RGB arrays, the project's in-memory image convention.

OpenCV decodes and encodes; BGR exists only inside these functions. Files are read as bytes first
so that paths with any characters work and a missing file raises `FileNotFoundError`.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from stereo.io.errors import ArrayFormatError, MalformedFileError


def _decode(path: Path, flags: int) -> np.ndarray:
    """Decode the image file at `path` with OpenCV `flags`; raise MalformedFileError when it cannot."""
    data = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    if data.size == 0:
        raise MalformedFileError(f"{path}: the file is empty, expected an image (PNG, JPEG, ...)")
    image = cv2.imdecode(data, flags)
    if image is None:
        raise MalformedFileError(f"{path}: not a readable image (OpenCV could not decode its {data.size} bytes)")
    return image


def read_rgb(path: str | Path) -> np.ndarray:
    """Read an image file as RGB `uint8` `H×W×3` (grey and palette expanded, alpha dropped, 16-bit scaled to 8)."""
    path = Path(path)
    return cv2.cvtColor(_decode(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def read_grey(path: str | Path) -> np.ndarray:
    """Read a single-channel image as `uint8` `H×W`; colour files are accepted only when every pixel is grey.

    Used for ground-truth maps and masks stored as grey or palette PNGs (OpenCV expands a palette
    to three channels, which must then be equal).
    """
    path = Path(path)
    image = _decode(path, cv2.IMREAD_UNCHANGED)
    if image.dtype != np.uint8:
        raise MalformedFileError(f"{path}: expected an 8-bit grey image, found dtype {image.dtype}")
    if image.ndim == 3:
        if image.shape[2] == 4:
            image = image[:, :, :3]
        if not (np.array_equal(image[:, :, 0], image[:, :, 1]) and np.array_equal(image[:, :, 0], image[:, :, 2])):
            raise MalformedFileError(f"{path}: expected a grey image, found colour pixels (channels differ)")
        image = image[:, :, 0]
    return np.ascontiguousarray(image)


def write_rgb(path: str | Path, image: np.ndarray) -> None:
    """Write an RGB `uint8` `H×W×3` (or grey `H×W`) array; the file extension picks the format."""
    path = Path(path)
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise ArrayFormatError(
            f"cannot write {path}: expected uint8 H×W×3 RGB or H×W grey, got {image.dtype} of shape {image.shape}"
        )
    bgr = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    try:
        ok, encoded = cv2.imencode(path.suffix or ".png", bgr)
    except cv2.error:  # OpenCV raises rather than returning False for an extension it has no encoder for
        ok = False
    if not ok:
        raise ArrayFormatError(f"cannot write {path}: OpenCV has no encoder for the extension {path.suffix!r}")
    path.write_bytes(encoded.tobytes())
