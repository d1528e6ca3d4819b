"""The paper's disparity metrics, computed per image over valid pixels and averaged over images.

Definitions (emcstereo_reference_facts.md §6, identical to the authors' train/val tools):
valid pixels have a finite ground truth `g` with `0 < g < max_disp` (192 by default); with
`err = |p − g|`:

- `epe` mean err; `rmse` √(mean err²) — the square root is taken per image;
- `d1_all` fraction with err > 3 **and** err / g > 0.05;
- `bad_0_5`, `bad_1`, `bad_2`, `bad_3`, `bad_4`, `bad_5` fraction with err > N (strict);
- `abs_rel` mean(err / g), `sq_rel` mean(err² / g), `rmse_log` √(mean (log p − log g)²),
  `delta1..3` fraction with max(p/g, g/p) < 1.25, 1.25², 1.25³ — all on **disparity**, the
  paper-compatible convention; p and g are clamped to ≥ 1e-6 in ratios and logs.

When the focal length (px) and baseline (m) are given, depth-based values are added with a
`_depth` suffix (Z = f·B/d): `abs_rel_depth` mean(|Zp − Zg| / Zg), `delta1_depth`, and the
absolute depth errors `mae_depth_m`, `rmse_depth_m` in metres. f·B cancels in the two relative
ones (|Zp − Zg| / Zg = |g/p − 1|), so `delta1_depth` equals `delta1`; `abs_rel_depth` differs
from the paper's `abs_rel`.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from stereo.pinhole import depth_from_disparity

DEFAULT_MAX_DISP = 192
CLAMP_MIN = 1e-6
BAD_THRESHOLDS: dict[str, float] = {
    "bad_0_5": 0.5,
    "bad_1": 1.0,
    "bad_2": 2.0,
    "bad_3": 3.0,
    "bad_4": 4.0,
    "bad_5": 5.0,
}
DELTA_BASE = 1.25


class NoValidPixelsError(ValueError):
    """An image has no pixel whose ground truth is finite and inside (0, max_disp): it cannot be scored."""


def valid_mask(gt: np.ndarray, max_disp: float = DEFAULT_MAX_DISP) -> np.ndarray:
    """Boolean `H×W` mask of the pixels that count: ground truth finite and in the open interval (0, max_disp)."""
    gt = np.asarray(gt)
    with np.errstate(invalid="ignore"):
        mask: np.ndarray = np.isfinite(gt) & (gt > 0) & (gt < max_disp)
    return mask


def _delta_fractions(pred: np.ndarray, gt: np.ndarray, suffix: str = "") -> dict[str, float]:
    """δ1..δ3: fractions of pixels with max(p/g, g/p) below 1.25, 1.25², 1.25³ (inputs already clamped)."""
    ratio = np.maximum(pred / gt, gt / pred)
    return {f"delta{k}{suffix}": float(np.mean(ratio < DELTA_BASE**k)) for k in (1, 2, 3)}


def _depth_metrics(pred: np.ndarray, gt: np.ndarray, focal_px: float, baseline_m: float) -> dict[str, float]:
    """Depth-based metrics from clamped disparities of the valid pixels (Z = f·B/d, metres)."""
    pred_z = depth_from_disparity(pred, focal_px, baseline_m)
    gt_z = depth_from_disparity(gt, focal_px, baseline_m)
    err_z = np.abs(pred_z - gt_z)
    return {
        "abs_rel_depth": float(np.mean(err_z / gt_z)),
        "delta1_depth": _delta_fractions(pred_z, gt_z, "_depth")["delta1_depth"],
        "mae_depth_m": float(np.mean(err_z)),
        "rmse_depth_m": float(np.sqrt(np.mean(err_z**2))),
    }


def image_metrics(
    pred: np.ndarray,
    gt: np.ndarray,
    *,
    max_disp: float = DEFAULT_MAX_DISP,
    focal_px: float | None = None,
    baseline_m: float | None = None,
) -> dict[str, float]:
    """Metrics of one predicted `H×W` disparity against its ground truth (pixels), over valid pixels.

    Returns the keys listed in the module docstring, plus `valid_pixels`. Raises
    `NoValidPixelsError` when no pixel is valid and `ValueError` for mismatched shapes, a
    non-finite prediction at a valid pixel, or only one of focal_px / baseline_m.
    """
    pred = np.asarray(pred)
    gt = np.asarray(gt)
    if pred.shape != gt.shape or pred.ndim != 2:
        raise ValueError(f"prediction {pred.shape} and ground truth {gt.shape} must be the same H×W shape")
    if (focal_px is None) != (baseline_m is None):
        raise ValueError(
            f"depth metrics need both focal_px and baseline_m, got focal_px={focal_px}, baseline_m={baseline_m}"
        )
    if focal_px is not None and baseline_m is not None and not (focal_px > 0 and baseline_m > 0):
        raise ValueError(f"focal_px and baseline_m must be positive, got {focal_px} and {baseline_m}")
    mask = valid_mask(gt, max_disp)
    n_valid = int(mask.sum())
    if n_valid == 0:
        raise NoValidPixelsError(
            f"no ground-truth pixel is finite and inside (0, {max_disp}); the image cannot be scored"
        )
    p = pred[mask].astype(np.float64)
    g = gt[mask].astype(np.float64)
    if not np.isfinite(p).all():
        raise ValueError(f"the prediction has {int((~np.isfinite(p)).sum())} non-finite values at valid pixels")
    err = np.abs(p - g)
    p_c = np.maximum(p, CLAMP_MIN)
    g_c = np.maximum(g, CLAMP_MIN)
    metrics = {
        "epe": float(np.mean(err)),
        "rmse": float(np.sqrt(np.mean(err**2))),
        "d1_all": float(np.mean((err > 3.0) & (err / g_c > 0.05))),
        **{name: float(np.mean(err > thr)) for name, thr in BAD_THRESHOLDS.items()},
        "abs_rel": float(np.mean(err / g_c)),
        "sq_rel": float(np.mean(err**2 / g_c)),
        "rmse_log": float(np.sqrt(np.mean((np.log(p_c) - np.log(g_c)) ** 2))),
        **_delta_fractions(p_c, g_c),
    }
    if focal_px is not None and baseline_m is not None:
        metrics.update(_depth_metrics(p_c, g_c, float(focal_px), float(baseline_m)))
    metrics["valid_pixels"] = float(n_valid)
    return metrics


class MetricAverager:
    """Averages per-image metrics over images (the sum of per-image values divided by the image count).

    Images without a valid pixel are counted in `skipped` rather than scored.
    """

    def __init__(
        self, *, max_disp: float = DEFAULT_MAX_DISP, focal_px: float | None = None, baseline_m: float | None = None
    ):
        self.max_disp = max_disp
        self.focal_px = focal_px
        self.baseline_m = baseline_m
        self.count = 0
        self.skipped = 0
        self._sums: dict[str, float] = {}

    def update(self, pred: np.ndarray, gt: np.ndarray) -> dict[str, float] | None:
        """Score one image, add it to the average and return its metrics (None when it had no valid pixel)."""
        try:
            metrics = image_metrics(
                pred, gt, max_disp=self.max_disp, focal_px=self.focal_px, baseline_m=self.baseline_m
            )
        except NoValidPixelsError:
            self.skipped += 1
            return None
        self.add(metrics)
        return metrics

    def add(self, metrics: Mapping[str, float]) -> None:
        """Add one image's metrics (every image must carry the same keys)."""
        if self.count and set(metrics) != set(self._sums):
            raise ValueError(f"metric keys {sorted(metrics)} differ from the earlier images' {sorted(self._sums)}")
        for key, value in metrics.items():
            self._sums[key] = self._sums.get(key, 0.0) + float(value)
        self.count += 1

    def mean(self) -> dict[str, float]:
        """Average of every metric over the images added so far (`valid_pixels` becomes the mean count)."""
        if self.count == 0:
            raise NoValidPixelsError(f"no image has been scored ({self.skipped} skipped without valid pixels)")
        return {key: total / self.count for key, total in self._sums.items()}
