"""Classical fallback backend: OpenCV semi-global matching, tuned for thin structures, no weights.

One full-resolution matcher pass on grey images plus a half-resolution check pass, so the stage
costs about what plain OpenCV SGBM costs (`benchmarks/sgbm_stage.py` measures it side by side;
table in benchmarks/RESULTS.md). Each step, what it costs and what it buys on the real pairs of
../shared/data/stereo (matched-pixel EPE / density, Tsukuba and the SceneFlow frame; measured when written):

- grey input (RGB → Y): the 3-way matcher on grey costs ~0.7× colour; accuracy is a wash (Tsukuba
  EPE 0.31 either way, Venus 0.25 grey against 0.33 colour, SceneFlow 2.50 against 2.52).
- a 3×3 block (thin branches are a few pixels wide; 5×5 fattens them: SceneFlow EPE 3.0 against
  2.5), the 3-way SGM variant, P1/P2 = 8/32·block²; uniqueness ratio 10 and speckle filtering
  (blobs < 50 px, range 2), without which SceneFlow EPE is 3.4–3.6 instead of 2.5 (~0 ms).
- left padding by the search range (+5–10 % matcher time): the leftmost `max_disp` columns, which
  OpenCV cannot match, lie in the padding, so the whole image gets a disparity (Tsukuba density
  0.94 → 0.98, all-pixel Bad-3 0.085 → 0.044).
- sub-pixel output (OpenCV's 1/16-px parabola fit), converted once to float32 px; window-edge
  rejection: a cost minimum on the first or last disparity searched is not a verified minimum
  (the truth may lie outside), so it is invalid — a narrow `compute_roi` window whose range misses
  the surface then reports "nothing here" instead of clamping to its edge.
- a left-right check against a right-referenced map from the mirrored pair matched at HALF
  resolution (~⅛ of the full pass's work, 13–16 % of the stage), tolerance `lr_tolerance` = 2 px:
  it rejects occlusions and mismatches, which are off by many pixels (Tsukuba EPE 0.31 → 0.26 at
  density 0.98 → 0.95; SceneFlow 2.50 → 1.33 at 0.82 → 0.76). The old backend ran the mirrored
  pass at full resolution (2× the matching time) for Tsukuba 0.25 / SceneFlow 1.43.
  OpenCV's internal `disp12MaxDiff` is no substitute: in 3-way mode it changes nothing (identical
  output for −1, 1 and 2). A visibility (ordering) check from the left map alone cost ~10 ms at
  HD720 for SceneFlow 2.5 → 2.3 only, a 3×3-median agreement filter ≤ 0.06 px: both left out.

Confidence (float32 `H×W` in [0, 1], 0 where invalid) is the left-right agreement
exp(−½ (Δ / (½ lr_tolerance))²), Δ = |d_left − d_right| px: 1 for perfect agreement, 0.61 at 1 px,
≈ 0.14 at the 2-px tolerance. On Tsukuba pixels with confidence < 0.5 have ~6× the EPE of the rest.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from stereo.backends.base import BackendConfigError, StereoResult, check_max_disp, stage_timings_ms, validate_pair
from stereo.backends.roi import crop_replicate, validate_window

SGBM_DISPARITY_STEP = 16
_FIXED_POINT = 16
ROI_CONTEXT_PX = 16
MATCHER_CACHE_SIZE = 64


def round_up_to_step(d_range: int) -> int:
    """The number of disparities OpenCV searches for a requested range: `d_range` rounded up to 16."""
    return -(-d_range // SGBM_DISPARITY_STEP) * SGBM_DISPARITY_STEP


class SGBMBackend:
    """OpenCV StereoSGBM (3-way, grey) with a half-resolution left-right check; disparities in px, invalid 0."""

    name = "sgbm"

    def __init__(
        self,
        max_disp: int = 192,
        *,
        block_size: int = 3,
        uniqueness_ratio: int = 10,
        speckle_window: int = 50,
        speckle_range: int = 2,
        lr_tolerance: float = 2.0,
        pad_left: bool = True,
        lr_check: bool = True,
        roi_lr_check: bool = True,
    ) -> None:
        """`pad_left` and `lr_check` switch off those steps (for speed, or to measure what they buy:
        benchmarks/sgbm_stage.py); without the check, confidence is 1 wherever the disparity is valid.
        `roi_lr_check`: run the check in `compute_roi` too (default). Without it a region keeps the
        thin branches the half-resolution check deletes (50 synthetic 640×360 scenes, roi mode with
        truth masks: cut points within 5 cm 70.2 % with it, 73.7 % without), but its confidence is 1
        wherever valid, so the cut points' confidence loses its stereo term and near-equal branches
        trade the target from frame to frame: kept on until confidence has another source."""
        check_max_disp(max_disp, "sgbm max_disp")
        if block_size < 1 or block_size % 2 == 0:
            raise BackendConfigError(f"sgbm block_size must be odd and positive, got {block_size}")
        if lr_tolerance <= 0:
            raise BackendConfigError(f"sgbm lr_tolerance must be positive, got {lr_tolerance}")
        self.max_disparity = max_disp
        self.lr_tolerance = float(lr_tolerance)
        self.pad_left, self.lr_check, self.roi_lr_check = pad_left, lr_check, roi_lr_check
        self._settings = (block_size, uniqueness_ratio, speckle_window, speckle_range)
        self._matchers: dict[tuple[int, int], cv2.StereoSGBM] = {}

    def compute(self, left: np.ndarray, right: np.ndarray) -> StereoResult:
        """Disparity (float32 px in (0, max_disp), 0 invalid) and LR-check confidence of a rectified RGB uint8 pair."""
        validate_pair(left, right)
        height, width = left.shape[:2]
        return self._window(left, right, (0, 0, width, height), 0, self.max_disparity, context=0, check=self.lr_check)

    def compute_roi(
        self, left: np.ndarray, right: np.ndarray, roi: tuple[int, int, int, int], d_min: int, d_range: int
    ) -> StereoResult:
        """Disparity of the left-image box `roi = (x0, y0, x1, y1)` searched over `[d_min, d_min + d_range)`.

        `left`, `right` are the full rectified frames; the matcher runs on a crop of them (see
        `_window`) with `minDisparity = d_min` and `numDisparities = 16·⌈d_range/16⌉`, post-processed
        as the whole frame is. Returns `(y1 − y0)×(x1 − x0)` maps, absolute disparity in px, 0 invalid,
        `max_disparity = d_min + d_range`.
        """
        roi, d_min, d_range = validate_window(left, right, roi, d_min, d_range)
        return self._window(
            left, right, roi, d_min, d_range, context=ROI_CONTEXT_PX, check=self.lr_check and self.roi_lr_check
        )

    def _window(
        self,
        left: np.ndarray,
        right: np.ndarray,
        roi: tuple[int, int, int, int],
        d_min: int,
        d_range: int,
        context: int,
        check: bool,
    ) -> StereoResult:
        """Match the box `roi` over `[d_min, d_min + d_range)` on a crop of the frames.

        The crop holds the box, `context` px around it for the SGM paths (clipped to the frame), and
        the `d_min + num_disparities` columns to its left that OpenCV needs before it matches a
        column — replicated where the frame ends, which is the whole frame's left padding. The
        right-referenced check pass needs as many columns beyond the box's right edge.
        """
        x0, y0, x1, y1 = roi
        height, width = left.shape[:2]
        num_disparities = round_up_to_step(d_range)
        start = time.perf_counter()
        rows = (max(y0 - context, 0), min(y1 + context, height))
        first = x0 - d_min - num_disparities - context
        if not self.pad_left:
            first = max(first, 0)
        main_width = min(x1 + context, width) - first
        grey_left, grey_right = (
            cv2.cvtColor(crop_replicate(image, rows, (first, x1 + num_disparities + context)), cv2.COLOR_RGB2GRAY)
            for image in (left, right)
        )
        prepared = time.perf_counter()
        raw = self._matcher(d_min, num_disparities).compute(grey_left[:, :main_width], grey_right[:, :main_width])
        disparity = window_disparity(raw, d_min, d_range)
        matched = time.perf_counter()
        if check:
            disp_right = self._right_disparity_half_resolution(grey_left, grey_right, d_min, d_range)
            checked = time.perf_counter()
            disparity, confidence = left_right_check(disparity, disp_right[:, :main_width], self.lr_tolerance)
        else:
            checked = time.perf_counter()
            confidence = (disparity > 0).astype(np.float32)
        box = (slice(y0 - rows[0], y1 - rows[0]), slice(x0 - first, x1 - first))
        disparity, confidence = np.ascontiguousarray(disparity[box]), np.ascontiguousarray(confidence[box])
        end = time.perf_counter()
        marks = [("prepare", prepared), ("match", matched), ("match_right_half", checked), ("postprocess", end)]
        return StereoResult(disparity, confidence, stage_timings_ms(start, marks), self.name, d_min + d_range)

    def _right_disparity_half_resolution(
        self, grey_left: np.ndarray, grey_right: np.ndarray, d_min: int, d_range: int
    ) -> np.ndarray:
        """Right-referenced disparity (float32 px at full resolution, 0 unmatched) of a grey `H×W` pair.

        The mirrored pair (right image as the reference) is matched at half resolution over
        `[⌊d_min/2⌋, ⌈(d_min + d_range)/2⌉)`: an eighth of the full pass's work, precise to ~1 px,
        enough to catch occlusions and mismatches, which are off by many pixels.
        """
        height, width = grey_left.shape
        half_size = ((width + 1) // 2, (height + 1) // 2)
        reference, other = (
            cv2.flip(cv2.resize(g, half_size, interpolation=cv2.INTER_AREA), 1) for g in (grey_right, grey_left)
        )
        low, high = d_min // 2, -(-(d_min + d_range) // 2)
        raw = cv2.flip(self._matcher(low, round_up_to_step(high - low)).compute(reference, other), 1)
        half = np.where(
            raw > low * _FIXED_POINT, raw.astype(np.float32) * np.float32(2.0 / _FIXED_POINT), np.float32(0.0)
        )
        return cv2.resize(half, (width, height), interpolation=cv2.INTER_NEAREST)

    def _matcher(self, d_min: int, num_disparities: int) -> cv2.StereoSGBM:
        """The 3-way grey matcher searching `[d_min, d_min + num_disparities)`, cached per range (oldest evicted)."""
        key = (d_min, num_disparities)
        if key not in self._matchers:
            if len(self._matchers) >= MATCHER_CACHE_SIZE:  # ROI windows move every frame: bound the cache
                del self._matchers[next(iter(self._matchers))]
            block_size, uniqueness_ratio, speckle_window, speckle_range = self._settings
            self._matchers[key] = cv2.StereoSGBM_create(
                minDisparity=d_min,
                numDisparities=num_disparities,
                blockSize=block_size,
                P1=8 * block_size**2,
                P2=32 * block_size**2,
                disp12MaxDiff=-1,  # a no-op in 3-way mode (measured); the explicit check replaces it
                uniquenessRatio=uniqueness_ratio,
                speckleWindowSize=speckle_window,
                speckleRange=speckle_range,
                preFilterCap=63,
                mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
            )
        return self._matchers[key]


def window_disparity(raw: np.ndarray, d_min: int, d_range: int) -> np.ndarray:
    """OpenCV's int16 1/16-px disparity → float32 px, 0 unless strictly inside the searched window.

    A cost minimum on the window's first or last disparity is not a verified minimum (the truth may
    lie outside), and OpenCV searches up to `16·⌈d_range/16⌉`: values ≥ `d_min + d_range` are outside.
    """
    last = min(d_min + round_up_to_step(d_range) - 1, d_min + d_range)
    inside = (raw > d_min * _FIXED_POINT) & (raw < last * _FIXED_POINT)
    disparity = cv2.multiply(raw, 1.0 / _FIXED_POINT, dtype=cv2.CV_32F)
    np.multiply(disparity, inside, out=disparity)
    return disparity


def left_right_check(disp_left: np.ndarray, disp_right: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Keep left disparities that the right-referenced map confirms within `tolerance` px.

    Both inputs are float32 `H×W` pixels, ≤ 0 where unmatched. Returns (disparity with rejected
    pixels 0, confidence in [0, 1] from the agreement, 0 where rejected).
    """
    height, width = disp_left.shape
    target_x = np.arange(width, dtype=np.float32)[None, :] - disp_left
    rows = np.empty_like(target_x)
    rows[:] = np.arange(height, dtype=np.float32)[:, None]
    # nearest-neighbour lookup of disp_right at (x − d, y); 0 (= unmatched) outside the image
    disp_seen = cv2.remap(disp_right, target_x, rows, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    diff = cv2.absdiff(disp_left, disp_seen)
    valid = (disp_left > 0) & (disp_seen > 0) & (diff <= tolerance)
    confidence = cv2.exp(cv2.multiply(diff, diff, scale=-0.5 / (0.5 * tolerance) ** 2))
    np.multiply(confidence, valid, out=confidence)
    return np.multiply(disp_left, valid, dtype=np.float32), confidence
