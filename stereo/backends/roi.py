"""Windowed disparity helpers shared by the backends: argument checks and edge-replicating crops.

A window is a pixel box `roi = (x0, y0, x1, y1)` of the left image (x1, y1 exclusive) and a search
range of absolute disparities `[d_min, d_min + d_range)`. To match it a backend needs left-image
columns to the left of the box (and, for the right image, columns shifted by the disparities): near
the frame's border those columns do not exist, so crops replicate the border pixel there, as the
whole-frame SGBM pads its left border.
"""

from __future__ import annotations

import operator

import cv2
import numpy as np

from stereo.backends.base import BackendConfigError, StereoInputError, validate_pair

Roi = tuple[int, int, int, int]


def _as_int(name: str, value: object) -> int:
    """`value` as a Python int, or BackendConfigError naming it (floats and bools are refused)."""
    if isinstance(value, bool):
        raise BackendConfigError(f"{name} must be an integer number of pixels, got {value!r}")
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise BackendConfigError(f"{name} must be an integer number of pixels, got {value!r}") from None


def validate_window(
    left: np.ndarray, right: np.ndarray, roi: object, d_min: object, d_range: object
) -> tuple[Roi, int, int]:
    """Check a `compute_roi` call; returns (roi, d_min, d_range) as ints.

    StereoInputError for a bad pair or a box that is not a non-empty `(x0, y0, x1, y1)` inside the
    `H×W` frame; BackendConfigError for d_min < 0 or d_range ≤ 0 (or non-integers).
    """
    validate_pair(left, right)
    height, width = left.shape[:2]
    try:
        x0, y0, x1, y1 = (operator.index(v) for v in roi)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise StereoInputError(f"roi must be four integers (x0, y0, x1, y1), got {roi!r}") from None
    if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
        raise StereoInputError(
            f"roi {(x0, y0, x1, y1)} must be a non-empty box inside the {width}×{height} frame: "
            f"0 ≤ x0 < x1 ≤ {width}, 0 ≤ y0 < y1 ≤ {height}"
        )
    d_min, d_range = _as_int("d_min", d_min), _as_int("d_range", d_range)
    if d_min < 0:
        raise BackendConfigError(f"d_min must be ≥ 0 px (disparities are positive), got {d_min}")
    if d_range <= 0:
        raise BackendConfigError(f"d_range must be > 0 px, got {d_range}")
    return (x0, y0, x1, y1), d_min, d_range


def crop_replicate(image: np.ndarray, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    """`image[r0:r1, c0:c1]` for any integer bounds, out-of-frame pixels replicating the nearest border.

    `image` is uint8 `H×W[×C]`; the result is `(r1 − r0)×(c1 − c0)[×C]`, C-contiguous (a copy).
    """
    height, width = image.shape[:2]
    (r0, r1), (c0, c1) = rows, cols
    top, bottom, left, right = max(r0, 0), min(r1, height), max(c0, 0), min(c1, width)
    if top < bottom and left < right:  # part of the box is in the frame: slice it and pad (fast path)
        inner = image[top:bottom, left:right]
        return cv2.copyMakeBorder(inner, top - r0, r1 - bottom, left - c0, c1 - right, cv2.BORDER_REPLICATE)
    row_index = np.clip(np.arange(r0, r1), 0, height - 1)
    col_index = np.clip(np.arange(c0, c1), 0, width - 1)
    return np.ascontiguousarray(image[row_index[:, None], col_index[None, :]])
