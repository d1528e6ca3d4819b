"""EXR depth maps (VirtualTree's UE5 renders): depth in the R channel, values as stored.

VirtualTree stores centimetres, with sky at about 65504 (the fp16 maximum); converting units and
masking sky is the dataset's job, not this reader's. Files may hold HALF or FLOAT channels.
The UE5 files carry three channels, R (depth), G and B (NaN everywhere): read with OpenCV they
are a 3-channel BGR image whose index 2 is the depth, which is how the authors' loader reads them.
The writer produces the same layout so that any reader of the real files reads ours.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import OpenEXR

from stereo.io.errors import ArrayFormatError, MalformedFileError

_PIXEL_TYPES = {"half": np.float16, "float": np.float32}


def read_exr_depth(path: str | Path, channel: str = "R") -> np.ndarray:
    """Read one channel (default R) of an EXR file as float32 `H×W`, in the file's units (VirtualTree: cm)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"EXR depth file {path} does not exist")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            channels = exr.channels()
            if channel not in channels:
                raise MalformedFileError(
                    f"{path}: EXR has no channel {channel!r}; channels present: {sorted(channels)}"
                )
            pixels = np.asarray(channels[channel].pixels)
    except RuntimeError as exc:
        raise MalformedFileError(f"{path}: not a readable OpenEXR file ({exc})") from exc
    if pixels.ndim != 2 or pixels.dtype not in (np.float16, np.float32):
        raise MalformedFileError(
            f"{path}: EXR channel {channel!r} holds {pixels.dtype} of shape {pixels.shape}, expected HALF or FLOAT H×W"
        )
    return pixels.astype(np.float32)


def write_exr_depth(path: str | Path, depth: np.ndarray, *, pixel_type: Literal["half", "float"] = "float") -> None:
    """Write float `H×W` depth (any unit; VirtualTree uses cm) in the UE5 layout: a ZIP-compressed EXR whose
    R channel is the depth and whose G and B channels are NaN.

    `pixel_type="half"` stores fp16 as UE5 does: values above 65504 become infinite.
    """
    path = Path(path)
    depth = np.asarray(depth)
    if pixel_type not in _PIXEL_TYPES:
        raise ArrayFormatError(f"cannot write {path}: pixel_type {pixel_type!r} must be 'half' or 'float'")
    if depth.ndim != 2 or depth.size == 0 or not np.issubdtype(depth.dtype, np.number):
        raise ArrayFormatError(
            f"cannot write {path}: expected a numeric H×W depth map, got {depth.dtype} {depth.shape}"
        )
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    pixels = np.ascontiguousarray(depth, dtype=_PIXEL_TYPES[pixel_type])
    unused = np.full_like(pixels, np.nan)
    with OpenEXR.File(header, {"R": pixels, "G": unused, "B": unused}) as exr:
        exr.write(str(path))
