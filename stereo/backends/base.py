"""The interface every stereo backend keeps: a rectified RGB pair in, disparity and confidence out."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

#: The numeric precisions a backend may be asked for (fp16/bf16: CUDA autocast, emcstereo only).
PRECISIONS: tuple[str, ...] = ("fp32", "fp16", "bf16")
#: A disparity search range is a whole number of these (SGBM's step; EMCStereo's ¼-resolution cost
#: volume is halved twice by its hourglass) …
MAX_DISP_STEP = 16
#: … and at most this many pixels (0.3 m at f = 2 400 px, B = 63 mm; each step costs matching time).
MAX_DISP_LIMIT = 512
#: What `max_disp` accepts, for messages.
MAX_DISP_EXPECTED = f"a positive multiple of {MAX_DISP_STEP} up to {MAX_DISP_LIMIT} px"


class StereoInputError(ValueError):
    """A stereo pair handed to a backend is not two equally sized uint8 H×W×3 RGB images."""


class BackendConfigError(ValueError):
    """A backend was asked for a setting it cannot honour (unknown name, bad max_disp, device, precision)."""


@dataclass(frozen=True)
class StereoResult:
    """What a backend returns for one pair.

    disparity: float32 `H×W`, pixels, left reference; invalid pixels are 0.
    confidence: float32 `H×W` in [0, 1]; 0 wherever the disparity is invalid.
    timing_ms: wall-clock milliseconds per stage, always with a `total` entry.
    """

    disparity: np.ndarray
    confidence: np.ndarray
    timing_ms: dict[str, float] = field(default_factory=dict)
    backend: str = ""
    max_disparity: int = 0


@runtime_checkable
class StereoBackend(Protocol):
    """A disparity estimator for rectified pairs; `max_disparity` is its search range in pixels."""

    name: str
    max_disparity: int

    def compute(self, left: np.ndarray, right: np.ndarray) -> StereoResult:
        """Disparity and confidence of the left image of a rectified RGB uint8 `H×W×3` pair."""
        ...

    def compute_roi(
        self, left: np.ndarray, right: np.ndarray, roi: tuple[int, int, int, int], d_min: int, d_range: int
    ) -> StereoResult:
        """Disparity of the box `roi = (x0, y0, x1, y1)` (x1, y1 exclusive) of the FULL left frame, searched
        over absolute disparities `[d_min, d_min + d_range)`: maps of the box's shape, absolute px,
        0 invalid, `max_disparity = d_min + d_range`. The backend crops (and edge-replicates) itself.
        A bad box raises StereoInputError; a range the backend cannot search, BackendConfigError."""
        ...


def is_valid_max_disp(value: object) -> bool:
    """Whether `value` is a usable disparity search range: an int multiple of `MAX_DISP_STEP` in
    (0, `MAX_DISP_LIMIT`]."""
    return (
        isinstance(value, int)
        and not isinstance(value, bool)
        and 0 < value <= MAX_DISP_LIMIT
        and value % MAX_DISP_STEP == 0
    )


def check_max_disp(value: object, name: str = "max_disp") -> int:
    """`value` when `is_valid_max_disp`, else `BackendConfigError` naming `name`: the one max_disp rule."""
    if not is_valid_max_disp(value):
        raise BackendConfigError(f"{name} = {value!r}: expected {MAX_DISP_EXPECTED}")
    return value  # type: ignore[return-value]


def stage_timings_ms(start: float, marks: list[tuple[str, float]]) -> dict[str, float]:
    """Milliseconds per stage from perf_counter marks [(stage, end time)], plus `total` from `start`."""
    timing: dict[str, float] = {}
    previous = start
    for stage, end in marks:
        timing[stage] = (end - previous) * 1e3
        previous = end
    timing["total"] = (previous - start) * 1e3
    return timing


def sanitize_dense_output(disparity: np.ndarray, confidence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A network's float `H×W` disparity and confidence as StereoResult wants them: float32,
    non-finite pixels invalid (0, confidence 0), confidence clipped to [0, 1]."""
    finite = np.isfinite(disparity) & np.isfinite(confidence)
    disparity = np.where(finite, disparity, 0.0).astype(np.float32)
    confidence = np.where(finite, np.clip(confidence, 0.0, 1.0), 0.0).astype(np.float32)
    return disparity, confidence


def validate_image(image: Any, side: str, error: type[ValueError] = StereoInputError) -> np.ndarray:
    """`image` itself when it is an RGB `uint8 H×W×3` array of at least 2×2 px, else `error` naming
    `side` ("left", "right") and what the image is instead."""
    if not isinstance(image, np.ndarray):
        raise error(f"{side} image must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise error(f"{side} image must be uint8 H×W×3 RGB, got {image.dtype} of shape {image.shape}")
    if image.shape[0] < 2 or image.shape[1] < 2:
        raise error(f"{side} image is empty: shape {image.shape}")
    return image


def validate_pair(left: Any, right: Any, error: type[ValueError] = StereoInputError) -> None:
    """The one check of a stereo pair, made once where a pair enters (a backend's `compute`, the
    pipeline, the API, the daemon): both `validate_image`, and the same size pixel for pixel.
    Raises `error` (default `StereoInputError`; the pipeline passes its `PipelineInputError`)."""
    validate_image(left, "left", error)
    validate_image(right, "right", error)
    if left.shape != right.shape:
        raise error(
            f"left {left.shape[1]}×{left.shape[0]} and right {right.shape[1]}×{right.shape[0]} images "
            "differ in size; a stereo pair must have the same shape, pixel for pixel"
        )
