"""Middlebury 2001 ground truth: 8-bit grey or palette PNGs holding disparity × scale, 0 = unknown.

The scale (Tsukuba 16, Venus 8) and the number of disparities are the two lines of `info.txt`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stereo.io.errors import MalformedFileError
from stereo.io.images import read_grey


@dataclass(frozen=True)
class Middlebury2001Info:
    """The `info.txt` of a Middlebury 2001 scene: grey level per pixel of disparity, disparity count."""

    scale: int
    ndisp: int


def read_middlebury2001_info(path: str | Path) -> Middlebury2001Info:
    """Parse a Middlebury 2001 `info.txt` (first line scale, second line number of disparities)."""
    path = Path(path)
    fields = path.read_text(encoding="ascii", errors="replace").split()
    try:
        scale, ndisp = int(fields[0]), int(fields[1])
    except (IndexError, ValueError) as exc:
        raise MalformedFileError(f"{path}: expected two integers (scale, ndisp), found {fields[:2]}") from exc
    if scale <= 0 or ndisp <= 0:
        raise MalformedFileError(f"{path}: expected two positive integers (scale, ndisp), found {fields[:2]}")
    return Middlebury2001Info(scale=scale, ndisp=ndisp)


def read_middlebury2001_disparity(path: str | Path, scale: float) -> np.ndarray:
    """Read a Middlebury 2001 ground-truth PNG as float32 `H×W` disparity in pixels (grey / scale, 0 = unknown)."""
    if scale <= 0:
        raise ValueError(f"Middlebury disparity scale must be positive, got {scale}")
    return read_grey(path).astype(np.float32) / np.float32(scale)
