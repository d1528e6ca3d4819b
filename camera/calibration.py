"""The stereo calibration every loader produces and the rectifier consumes, and its errors.

Conventions (OpenCV's): `K1`, `K2` are 3×3 pinhole matrices in pixels at `image_size`; `D1`, `D2`
are OpenCV distortion vectors (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [τx τy]]]]); `R`, `T` map a
point from the left camera frame to the right one, `x_right = R @ x_left + T`, with `T` in metres.
For a right camera that sits to the right of the left one, `T[0]` is therefore negative
(about -baseline).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: Accepted lengths of an OpenCV distortion vector.
DISTORTION_LENGTHS = (4, 5, 8, 12, 14)

#: Largest accepted image width or height in pixels. Rectification maps cost ~10 bytes a pixel
#: per view, so an 8192×8192 calibration already needs 1.3 GB; stereo cameras this project
#: supports are at most 2208 px wide (ZED 2K).
MAX_IMAGE_SIDE_PX = 8192


class CalibrationError(ValueError):
    """A calibration file or value is unusable; the message names the file, the key and what was expected."""

    def __init__(self, source: str | Path, key: str, problem: str, expected: str) -> None:
        self.source = str(source)
        self.key = key
        self.problem = problem
        self.expected = expected
        super().__init__(f"{self.source}: {key}: {problem} (expected {expected})")


class FrameSizeError(CalibrationError):
    """A frame handed to the rectifier does not have the size the calibration was made for."""


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """Raw (or already rectified) intrinsics and extrinsics of a stereo pair.

    Arrays: `K1`, `K2` (3, 3) px; `D1`, `D2` (n,) OpenCV order; `R` (3, 3); `T` (3,) metres,
    left→right (`x_right = R @ x_left + T`). `image_size` is (width, height) in pixels.
    `is_rectified` marks images that are already rectified (KITTI `P_rect`, focal/baseline-only):
    the rectifier then leaves pixels untouched. `source` names where the values came from, for
    error messages.
    """

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    image_size: tuple[int, int]
    is_rectified: bool = False
    source: str = field(default="<memory>")

    def __post_init__(self) -> None:
        arrays = {
            "K1": (self.K1, (3, 3)),
            "K2": (self.K2, (3, 3)),
            "R": (self.R, (3, 3)),
            "T": (self.T, (3,)),
            "D1": (self.D1, None),
            "D2": (self.D2, None),
        }
        for key, (value, shape) in arrays.items():
            array = np.asarray(value, dtype=np.float64)
            if shape is None:
                array = array.reshape(-1)
                if array.size not in DISTORTION_LENGTHS:
                    raise CalibrationError(
                        self.source,
                        key,
                        f"has {array.size} coefficients",
                        f"one of {DISTORTION_LENGTHS} OpenCV distortion coefficients",
                    )
            elif array.size == int(np.prod(shape)):
                array = array.reshape(shape)
            else:
                raise CalibrationError(self.source, key, f"has shape {array.shape}", f"shape {shape}")
            if not np.all(np.isfinite(array)):
                raise CalibrationError(
                    self.source, key, f"contains a non-finite value {array.tolist()}", "finite numbers"
                )
            array.setflags(write=False)
            object.__setattr__(self, key, array)
        try:
            width, height = (int(v) for v in self.image_size)
        except (TypeError, ValueError):
            raise CalibrationError(
                self.source, "image_size", f"is {self.image_size!r}", "(width, height) in pixels"
            ) from None
        if not (0 < width <= MAX_IMAGE_SIDE_PX and 0 < height <= MAX_IMAGE_SIDE_PX):
            raise CalibrationError(
                self.source,
                "image_size",
                f"is {self.image_size}",
                f"a positive (width, height) in pixels, each at most {MAX_IMAGE_SIDE_PX}",
            )
        object.__setattr__(self, "image_size", (width, height))
        for key in ("K1", "K2"):
            k = getattr(self, key)
            if k[0, 0] <= 0 or k[1, 1] <= 0:
                raise CalibrationError(
                    self.source,
                    key,
                    f"has focal lengths fx={k[0, 0]}, fy={k[1, 1]}",
                    "positive focal lengths in pixels",
                )
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-4) or np.linalg.det(self.R) < 0:
            raise CalibrationError(
                self.source,
                "R",
                f"is not a rotation matrix: {self.R.tolist()}",
                "an orthonormal 3×3 matrix with determinant +1",
            )
        if self.baseline_m <= 0:
            raise CalibrationError(self.source, "T", f"is {self.T.tolist()}", "a non-zero translation in metres")

    @property
    def baseline_m(self) -> float:
        """Distance between the two optical centres, metres."""
        return float(np.linalg.norm(self.T))

    @property
    def width(self) -> int:
        """Image width in pixels."""
        return self.image_size[0]

    @property
    def height(self) -> int:
        """Image height in pixels."""
        return self.image_size[1]

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, StereoCalibration):
            return NotImplemented
        return (
            self.image_size == other.image_size
            and self.is_rectified == other.is_rectified
            and all(np.array_equal(getattr(self, k), getattr(other, k)) for k in ("K1", "D1", "K2", "D2", "R", "T"))
        )

    __hash__ = None  # type: ignore[assignment]


def require_image_size(calibration: StereoCalibration, size: tuple[int, int]) -> None:
    """Raise FrameSizeError unless the calibration was made for images of `size` = (width, height) px.

    Called before a `Rectifier` is built: its maps are sized by the calibration, so a file that
    claims 8000×8000 px for 320×256 images would otherwise allocate gigabytes first.
    """
    if tuple(calibration.image_size) != tuple(size):
        width, height = calibration.image_size
        raise FrameSizeError(
            calibration.source,
            "image size",
            f"is {width}×{height} px",
            f"{size[0]}×{size[1]} px, the size of the images; use the calibration "
            "of this resolution (e.g. --resolution)",
        )


def camera_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """A 3×3 pinhole matrix (pixels) from focal lengths and principal point."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def from_rectified(
    focal_px: float,
    cx: float,
    cy: float,
    baseline_m: float,
    size: tuple[int, int],
    *,
    cx_right: float | None = None,
    source: str = "<rectified>",
) -> StereoCalibration:
    """Calibration of an already rectified pair known only by focal length, principal point and baseline.

    `focal_px`, `cx`, `cy` in pixels at `size` = (width, height); `baseline_m` in metres (> 0);
    `cx_right` is the right image's principal point column when it differs (KITTI-style offsets).
    """
    values = {"focal_px": focal_px, "cx": cx, "cy": cy, "baseline_m": baseline_m}
    for key, value in values.items():
        if not np.isfinite(value):
            raise CalibrationError(source, key, f"is {value}", "a finite number")
    if focal_px <= 0:
        raise CalibrationError(source, "focal_px", f"is {focal_px}", "a positive focal length in pixels")
    if baseline_m <= 0:
        raise CalibrationError(source, "baseline_m", f"is {baseline_m}", "a positive baseline in metres")
    k1 = camera_matrix(focal_px, focal_px, cx, cy)
    k2 = camera_matrix(focal_px, focal_px, cx if cx_right is None else cx_right, cy)
    zeros = np.zeros(5)
    return StereoCalibration(
        k1,
        zeros,
        k2,
        zeros,
        np.eye(3),
        np.array([-baseline_m, 0.0, 0.0]),
        (size[0], size[1]),
        is_rectified=True,
        source=source,
    )


def read_calibration_text(path: str | Path) -> str:
    """The text of a calibration file, without a UTF-8 byte-order mark and with any line ending."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise CalibrationError(
            path, "<file>", f"cannot be read ({error.strerror})", "an existing, readable calibration file"
        ) from error
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        raise CalibrationError(
            path, "<file>", f"is not UTF-8 text (byte {error.start})", "a text calibration file"
        ) from error
    return "\n".join(text.splitlines())


def parse_number(source: str | Path, key: str, text: str) -> float:
    """A finite float from a calibration value, or a CalibrationError naming the key."""
    try:
        value = float(text.strip())
    except ValueError:
        hint = " with '.' as the decimal mark" if "," in text else ""
        raise CalibrationError(source, key, f"is {text.strip()!r}, not a number", f"a decimal number{hint}") from None
    if not np.isfinite(value):
        raise CalibrationError(source, key, f"is {text.strip()!r}", "a finite number")
    return value
