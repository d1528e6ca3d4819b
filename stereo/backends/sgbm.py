"""Classical fallback backend: OpenCV semi-global matching, tuned for thin structures, no weights.

Choices, measured on the Middlebury 2001 and SceneFlow pairs in ../shared/data/stereo:
- a 3×3 matching block (thin branches are a few pixels wide; larger blocks fatten them), the
  3-way SGM variant (near full 8-path quality at a fraction of the time), P1/P2 = 8/32·3·block²;
- the images are padded on the left by `max_disp` columns, so that the leftmost columns, which
  OpenCV cannot match, lie in the padding and the whole image gets a disparity;
- sub-pixel output (OpenCV's 1/16-px parabola fit), speckle filtering of small blobs;
- an explicit left-right consistency check: the right-referenced map comes from the same matcher
  run on the mirrored pair; a pixel whose two disparities differ by more than `lr_tolerance` px is
  invalid (0, confidence 0). Confidence of a valid pixel is exp(−½ (diff / (½ lr_tolerance))²),
  so 1 for perfect agreement and ≈ 0.14 at the tolerance.
"""
from __future__ import annotations

import time

import cv2
import numpy as np

from stereo.backends.base import BackendConfigError, StereoResult, stage_timings_ms, validate_pair

SGBM_DISPARITY_STEP = 16
_FIXED_POINT = 16.0


class SGBMBackend:
    """OpenCV StereoSGBM with left-right check; disparities in [0, max_disp) px, invalid 0."""

    name = "sgbm"

    def __init__(
        self,
        max_disp: int = 192,
        *,
        block_size: int = 3,
        uniqueness_ratio: int = 10,
        speckle_window: int = 50,
        speckle_range: int = 2,
        lr_tolerance: float = 1.0,
    ) -> None:
        if not isinstance(max_disp, int) or max_disp <= 0 or max_disp % SGBM_DISPARITY_STEP:
            raise BackendConfigError(f"sgbm max_disp must be a positive multiple of {SGBM_DISPARITY_STEP}, got {max_disp!r}")
        if block_size < 1 or block_size % 2 == 0:
            raise BackendConfigError(f"sgbm block_size must be odd and positive, got {block_size}")
        if lr_tolerance <= 0:
            raise BackendConfigError(f"sgbm lr_tolerance must be positive, got {lr_tolerance}")
        self.max_disparity = max_disp
        self.lr_tolerance = float(lr_tolerance)
        channels = 3
        self._matcher = cv2.StereoSGBM_create(
            minDisparity=0,
            numDisparities=max_disp,
            blockSize=block_size,
            P1=8 * channels * block_size**2,
            P2=32 * channels * block_size**2,
            disp12MaxDiff=-1,  # the explicit check below replaces OpenCV's internal one
            uniquenessRatio=uniqueness_ratio,
            speckleWindowSize=speckle_window,
            speckleRange=speckle_range,
            preFilterCap=63,
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        )

    def _match(self, reference: np.ndarray, other: np.ndarray) -> np.ndarray:
        """Disparity `H×W` of `reference` (float32 px, negative = no match), with the left border padded."""
        pad = self.max_disparity
        reference = cv2.copyMakeBorder(reference, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
        other = cv2.copyMakeBorder(other, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
        return self._matcher.compute(reference, other)[:, pad:].astype(np.float32) / _FIXED_POINT

    def compute(self, left: np.ndarray, right: np.ndarray) -> StereoResult:
        """Disparity (float32 px, 0 invalid) and LR-agreement confidence of a rectified RGB uint8 pair."""
        validate_pair(left, right)
        start = time.perf_counter()
        disp_left = self._match(left, right)
        matched = time.perf_counter()
        # Right-referenced disparity: mirror the pair so the right image becomes a left reference.
        disp_right = self._match(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]))[:, ::-1]
        matched_right = time.perf_counter()
        disparity, confidence = left_right_check(disp_left, disp_right, self.lr_tolerance)
        end = time.perf_counter()
        timing = stage_timings_ms(start, [("match_left", matched), ("match_right", matched_right), ("lr_check", end)])
        return StereoResult(disparity, confidence, timing, self.name, self.max_disparity)


def left_right_check(disp_left: np.ndarray, disp_right: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Keep left disparities that the right-referenced map confirms within `tolerance` px.

    Both inputs are float32 `H×W` pixels, ≤ 0 where unmatched. Returns (disparity with rejected
    pixels 0, confidence in [0, 1] from the agreement, 0 where rejected).
    """
    width = disp_left.shape[1]
    target_x = np.arange(width, dtype=np.float32)[None, :] - disp_left
    column = np.clip(np.rint(target_x), 0, width - 1).astype(np.intp)
    disp_seen = np.take_along_axis(disp_right, column, axis=1)
    diff = np.abs(disp_left - disp_seen)
    valid = (disp_left > 0) & (disp_seen > 0) & (target_x >= -0.5) & (diff <= tolerance)
    sigma = 0.5 * tolerance
    confidence = np.where(valid, np.exp(-0.5 * (diff / sigma) ** 2), 0.0).astype(np.float32)
    disparity = np.where(valid, disp_left, 0.0).astype(np.float32)
    return disparity, confidence
