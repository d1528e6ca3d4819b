"""Small, valid `FrameResult`s for tests of the consumers (MAVLink, overlay, Foxglove, the API's /latest)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from branchrange.core.frame_result import Branch, CameraInfo, Frame, FrameResult, MasksInfo, StereoInfo


def branch(
    id: int,
    cut_point_m: Sequence[float],
    *,
    confidence: float = 1.0,
    pixel: Sequence[float] = (0.0, 0.0),
    axis: Sequence[float] = (1.0, 0.0, 0.0),
    diameter_m: float = 0.02,
    mask_id: int | None = None,
) -> Branch:
    """A branch at `cut_point_m` (distance its norm, base 5 cm back along `axis`)."""
    cut = np.asarray(cut_point_m, dtype=float)
    x, y, z = (float(v) for v in cut)
    bx, by, bz = (float(v) for v in cut - 0.05 * np.asarray(axis, dtype=float))
    ax, ay, az = (float(v) for v in axis)
    return Branch(
        id=id,
        mask_id=id if mask_id is None else mask_id,
        cut_point_m=(x, y, z),
        distance_m=float(np.linalg.norm(cut)),
        pixel=(float(pixel[0]), float(pixel[1])),
        diameter_m=diameter_m,
        axis=(ax, ay, az),
        base_m=(bx, by, bz),
        confidence=confidence,
        valid_fraction=1.0,
        residual_m=0.0,
        points=100,
    )


def frame_result(
    branches: Sequence[Branch] = (),
    target_id: int | None = None,
    *,
    index: int = 0,
    timestamp_ns: int = 0,
    width: int = 64,
    height: int = 48,
    focal_px: float = 700.0,
    baseline_m: float = 0.063,
    reason: str | None = None,
) -> FrameResult:
    """A result of `branches` (target `target_id`) in a `width × height` frame, timing 1 ms; the camera a ZED Mini
    at HD720 (f 700 px, B 63 mm), so that a cut point within ~1.5 m is known to a target's σ bound."""
    return FrameResult(
        frame=Frame(index, timestamp_ns, width, height),
        camera=CameraInfo(focal_px, baseline_m, (width - 1) / 2, (height - 1) / 2),
        stereo=StereoInfo("sgbm", 64, 1.0),
        timing_ms={"total": 1.0},
        masks=MasksInfo("array", len(branches), False),
        branches=tuple(branches),
        dropped=(),
        target_id=target_id,
        reason=reason,
    )
