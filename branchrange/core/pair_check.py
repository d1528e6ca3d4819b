"""Is a stereo pair really rectified? Vertical misalignment from feature matches, before trusting depth.

Stereo matchers search along image rows only: a pair whose rows are a few pixels apart (raw
frames, a wrong or stale calibration, a camera knocked on its mount) gives a few percent of
valid disparity and confident nonsense. `check_rectification` matches ORB features between the
two images (Lowe ratio test), keeps the matches whose vertical offset agrees with the majority
(median ± max(2 px, 3 MAD)) and reports the median |dy| of those inliers:

- ≤ `WARN_DY_PX` (1 px): fine;
- above it: a warning, with how to fix it;
- above `REFUSE_DY_PX` (8 px): the pair is refused — at 8 px rows apart, SGBM's and EMCStereo's
  row-wise search (and their 3–5 px matching windows) find no true match for most pixels;
- fewer than `MIN_MATCHES` inliers (textureless, dark, very different views): unknown, no verdict.

Cost: ~10–25 ms at 640×360 on one core (ORB on ≤ 1000 features); images wider than
`MAX_WIDTH_PX` are checked at reduced size and the offset scaled back.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

WARN_DY_PX = 1.0
REFUSE_DY_PX = 8.0
MIN_MATCHES = 20
MAX_WIDTH_PX = 1280
RATIO = 0.75
FIX_HINT = (
    "rectify the pair (give the raw frames with their calibration file: --calib, or the API's "
    "calibration upload) or recalibrate the camera"
)


class PairRefusedError(ValueError):
    """The pair's rows are too far apart for stereo; the message gives the offset and the fix."""


@dataclass(frozen=True)
class PairCheck:
    """Result of `check_rectification`.

    `median_dy_px`: median |y_left − y_right| of the inlier matches (pixels at the input
    resolution; None when unknown); `matches`: inlier count; `status`: 'ok', 'warning',
    'refused' or 'unknown'; `message`: a sentence for logs and users.
    """

    median_dy_px: float | None
    matches: int
    status: str
    message: str

    def raise_if_refused(self) -> None:
        """`PairRefusedError` when the pair must not be used for stereo."""
        if self.status == "refused":
            raise PairRefusedError(self.message)

    def log(self, logger: logging.Logger) -> None:
        """Log the verdict: a warning when the pair is misaligned or refused, debug otherwise (the daemon's hook)."""
        level = logging.WARNING if self.status in ("warning", "refused") else logging.DEBUG
        logger.log(level, "pair check: %s", self.message)


def _gray(image: np.ndarray, scale: float) -> np.ndarray:
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if scale != 1.0:
        gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return gray


def vertical_offsets(left: np.ndarray, right: np.ndarray, features: int = 1000) -> np.ndarray:
    """y_left − y_right `(N,)` in pixels of the ratio-test ORB matches of a pair (`uint8 H×W[×3]`)."""
    scale = min(1.0, MAX_WIDTH_PX / left.shape[1])
    orb = cv2.ORB.create(nfeatures=features)
    kp_l, desc_l = orb.detectAndCompute(_gray(left, scale), None)
    kp_r, desc_r = orb.detectAndCompute(_gray(right, scale), None)
    if desc_l is None or desc_r is None or len(kp_l) < 2 or len(kp_r) < 2:
        return np.zeros(0)
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(desc_l, desc_r, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
    dy = np.array([kp_l[m.queryIdx].pt[1] - kp_r[m.trainIdx].pt[1] for m in good], dtype=np.float64)
    offsets: np.ndarray = dy / scale
    return offsets


def check_rectification(left: np.ndarray, right: np.ndarray) -> PairCheck:
    """How far apart the rows of a stereo pair are (see the module docstring for the thresholds).

    The pair is one its caller validated (`stereo.backends.validate_pair`): RGB `uint8 H×W×3`, same size.
    """
    dy = vertical_offsets(left, right)
    if dy.size:
        centre = float(np.median(dy))
        spread = max(2.0, 3.0 * 1.4826 * float(np.median(np.abs(dy - centre))))
        dy = dy[np.abs(dy - centre) <= spread]
    if dy.size < MIN_MATCHES:
        return PairCheck(
            None,
            int(dy.size),
            "unknown",
            f"only {dy.size} consistent feature matches (need {MIN_MATCHES}): rectification not checked",
        )
    median = float(np.median(np.abs(dy)))
    where = f"rows of the pair are {median:.1f} px apart (median |dy| of {dy.size} feature matches)"
    if median > REFUSE_DY_PX:
        return PairCheck(
            median,
            int(dy.size),
            "refused",
            f"{where}, above the {REFUSE_DY_PX:g} px limit: stereo along rows cannot work; {FIX_HINT}",
        )
    if median > WARN_DY_PX:
        return PairCheck(
            median,
            int(dy.size),
            "warning",
            f"{where}, above {WARN_DY_PX:g} px: depth will be sparse and unreliable; {FIX_HINT}",
        )
    return PairCheck(median, int(dy.size), "ok", f"{where}: rectified")
