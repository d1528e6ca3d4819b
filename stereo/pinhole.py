"""The pinhole relations of a rectified stereo pair, written once for every package that needs them.

Depth and disparity: `Z = f·B/d` (and, solved for the disparity, `d = f·B/Z`), with `f` the rectified
focal length in pixels and `B` the baseline in the unit `Z` comes out in. Projection of points in the
rectified left camera frame (x right, y down, z forward): `(u, v) = f·(X, Y)/Z + (cx, cy)` pixels.
Callers pass valid values only (finite, positive disparity or depth; points in front of the camera):
what counts as invalid, and what stands in for it, differs between them.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

#: An array in gives an array of the same shape out, a number gives a number.
ArrayOrFloat = TypeVar("ArrayOrFloat", np.ndarray, float)


def depth_from_disparity(disparity: ArrayOrFloat, focal_px: float, baseline: float) -> ArrayOrFloat:
    """Depth `Z = f·B/d` (the baseline's unit) of disparities `d` in pixels (any shape; d > 0)."""
    return focal_px * baseline / disparity


def disparity_from_depth(depth: ArrayOrFloat, focal_px: float, baseline: float) -> ArrayOrFloat:
    """Disparity `d = f·B/Z` in pixels of depths `Z` in the baseline's unit (any shape; Z > 0)."""
    return depth_from_disparity(depth, focal_px, baseline)


def project(points: np.ndarray, focal_px: float, cx: float, cy: float) -> np.ndarray:
    """Pixel coordinates `(N, 2)` as (u, v) of points `(N, 3)` in the camera frame (z > 0, not checked)."""
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    z = points[:, 2]
    return np.stack([focal_px * points[:, 0] / z + cx, focal_px * points[:, 1] / z + cy], axis=-1)
