"""Rectification of raw stereo pairs: maps computed once from a calibration, applied to every frame."""

from __future__ import annotations

import cv2
import numpy as np

from camera.calibration import FrameSizeError, StereoCalibration


def rectified_projections(calibration: StereoCalibration) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """P1, P2 (3×4) and Q (4×4) of an already rectified calibration, laid out as cv2.stereoRectify lays them out."""
    p1 = np.hstack([calibration.K1, np.zeros((3, 1))])
    p2 = np.hstack([calibration.K2, calibration.K2 @ calibration.T.reshape(3, 1)])
    fx, cx1, cy = p1[0, 0], p1[0, 2], p1[1, 2]
    tx = p2[0, 3] / p2[0, 0]
    q = np.array(
        [
            [1.0, 0.0, 0.0, -cx1],
            [0.0, 1.0, 0.0, -cy],
            [0.0, 0.0, 0.0, fx],
            [0.0, 0.0, -1.0 / tx, (cx1 - calibration.K2[0, 2]) / tx],
        ]
    )
    return p1, p2, q


class Rectifier:
    """Turns raw left/right frames into a rectified pair with a known focal length and baseline.

    Uses cv2.stereoRectify with CALIB_ZERO_DISPARITY and alpha 0 (only valid pixels, no black
    borders) at the calibration's image size; the remap tables are built once here and reused for
    every frame. An already rectified calibration (`is_rectified`) leaves pixels untouched.
    Rectified left frame: OpenCV axes; depth `Z = focal_px * baseline_m / disparity`
    (`stereo.pinhole.depth_from_disparity`).
    """

    def __init__(self, calibration: StereoCalibration) -> None:
        self.calibration = calibration
        size = calibration.image_size
        # Rotations (3×3), projections (3×4) and the reprojection matrix Q (4×4) of the rectified pair.
        self.R1: np.ndarray
        self.R2: np.ndarray
        self.P1: np.ndarray
        self.P2: np.ndarray
        self.Q: np.ndarray
        if calibration.is_rectified:
            self.R1 = self.R2 = np.eye(3)
            self.P1, self.P2, self.Q = rectified_projections(calibration)
            self._maps = None
        else:
            c = calibration
            self.R1, self.R2, self.P1, self.P2, self.Q, _, _ = cv2.stereoRectify(
                c.K1,
                c.D1,
                c.K2,
                c.D2,
                size,
                c.R,
                c.T.reshape(3, 1),
                flags=cv2.CALIB_ZERO_DISPARITY,
                alpha=0.0,
                newImageSize=size,
            )
            self._maps = (
                cv2.initUndistortRectifyMap(c.K1, c.D1, self.R1, self.P1, size, cv2.CV_16SC2),
                cv2.initUndistortRectifyMap(c.K2, c.D2, self.R2, self.P2, size, cv2.CV_16SC2),
            )
        self._label_maps: tuple[np.ndarray, np.ndarray] | None = None  # built on the first mask
        for name in ("R1", "R2", "P1", "P2", "Q"):
            getattr(self, name).setflags(write=False)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of input and rectified frames, pixels."""
        return self.calibration.image_size

    @property
    def focal_px(self) -> float:
        """Rectified focal length, pixels (the same for both views)."""
        return float(self.P1[0, 0])

    @property
    def baseline_m(self) -> float:
        """Rectified baseline, metres: |P2[0,3] / P2[0,0]|."""
        return float(abs(self.P2[0, 3] / self.P2[0, 0]))

    @property
    def principal_point(self) -> tuple[float, float]:
        """Rectified principal point (cx, cy) of the left view, pixels."""
        return float(self.P1[0, 2]), float(self.P1[1, 2])

    def check_frame(self, image: np.ndarray, which: str) -> None:
        """Raise FrameSizeError unless `image` is an H×W×3 uint8 frame of the calibration's size."""
        width, height = self.size
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise FrameSizeError(
                self.calibration.source,
                f"{which} frame",
                f"has shape {image.shape} and dtype {image.dtype}",
                "an H×W×3 uint8 RGB image",
            )
        if image.shape[:2] != (height, width):
            raise FrameSizeError(
                self.calibration.source,
                f"{which} frame",
                f"is {image.shape[1]}×{image.shape[0]} px",
                f"{width}×{height} px, the size the calibration was made for",
            )

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rectified (left, right), each H×W×3 uint8 RGB like the inputs (bilinear interpolation)."""
        self.check_frame(left, "left")
        self.check_frame(right, "right")
        if self._maps is None:
            return left, right
        (left_a, left_b), (right_a, right_b) = self._maps
        return (cv2.remap(left, left_a, left_b, cv2.INTER_LINEAR), cv2.remap(right, right_a, right_b, cv2.INTER_LINEAR))

    def rectify_labels(self, labels: np.ndarray) -> np.ndarray:
        """Instance labels (`H×W` ids) drawn on the raw left image, moved onto the rectified left image:
        `int32 H×W`, each pixel the id nearest to where it came from, 0 where it came from outside.

        The float remap tables (exact positions: ids must not blend) are built on the first call and kept,
        so a mask per frame costs a remap, not a map rebuild. An already rectified calibration leaves
        the labels as they are.
        """
        if self._maps is None:
            return labels
        if self._label_maps is None:
            c = self.calibration
            self._label_maps = cv2.initUndistortRectifyMap(c.K1, c.D1, self.R1, self.P1, c.image_size, cv2.CV_32FC1)
        map_x, map_y = self._label_maps
        return cv2.remap(
            labels.astype(np.float32), map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        ).astype(np.int32)
