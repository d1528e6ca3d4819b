"""ONNX Runtime backend: runs an EMCStereo graph written by `emcstereo export --onnx` (stereo.export).

The graph has one padded input size and one disparity range (read from its metadata); pairs up to
that size are edge-padded at the top and right to it, as `stereo.padding` pads for the network.
"""

from __future__ import annotations

import os
import time

import numpy as np
import torch

from stereo.backends.base import (
    BackendConfigError,
    StereoInputError,
    StereoResult,
    sanitize_dense_output,
    stage_timings_ms,
    validate_pair,
)
from stereo.backends.emcstereo import normalize_images
from stereo.export import METADATA_KEYS
from stereo.onnx_runtime import import_onnxruntime
from stereo.padding import Padding, pad_image, unpad


class OnnxBackend:
    """EMCStereo through ONNX Runtime's CPU provider; disparity and confidence as the emcstereo backend."""

    name = "onnx"

    def __init__(self, path: str | os.PathLike[str], *, threads: int | None = None) -> None:
        try:
            onnxruntime = import_onnxruntime()
        except ImportError as exc:
            raise BackendConfigError(
                "the onnx backend needs onnxruntime (a dependency of branchrange: pip install onnxruntime)"
            ) from exc
        options = onnxruntime.SessionOptions()
        if threads is not None:
            options.intra_op_num_threads = threads
        try:
            self._session = onnxruntime.InferenceSession(os.fspath(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own untyped errors for missing or corrupt files
            raise BackendConfigError(f"cannot load ONNX model {path}: {exc}") from exc
        metadata = self._session.get_modelmeta().custom_metadata_map
        missing = [key for key in METADATA_KEYS if key not in metadata]
        if missing:
            raise BackendConfigError(
                f"ONNX model {path} lacks metadata {missing}: export it with `emcstereo export --onnx`"
            )
        self.height, self.width, self.max_disparity = (int(metadata[key]) for key in METADATA_KEYS)

    def compute(self, left: np.ndarray, right: np.ndarray) -> StereoResult:
        """Disparity (float32 px, 0 where non-finite) and confidence in [0, 1] of a rectified RGB pair."""
        validate_pair(left, right)
        height, width = left.shape[:2]
        if height > self.height or width > self.width:
            raise StereoInputError(
                f"pair of {height}×{width} is larger than the {self.height}×{self.width} "
                "the ONNX model was exported for; export it again for this size"
            )
        padding = Padding(top=self.height - height, right=self.width - width, height=height, width=width)
        start = time.perf_counter()
        with torch.inference_mode():
            images = pad_image(normalize_images(np.stack([left, right]), torch.device("cpu")), padding).numpy()
        prepared = time.perf_counter()
        disparity, confidence = self._session.run(None, {"left": images[:1], "right": images[1:]})
        inferred = time.perf_counter()
        disparity, confidence = sanitize_dense_output(unpad(disparity[0], padding), unpad(confidence[0], padding))
        end = time.perf_counter()
        timing = stage_timings_ms(start, [("preprocess", prepared), ("network", inferred), ("postprocess", end)])
        return StereoResult(disparity, confidence, timing, self.name, self.max_disparity)

    def compute_roi(
        self, left: np.ndarray, right: np.ndarray, roi: tuple[int, int, int, int], d_min: int, d_range: int
    ) -> StereoResult:
        """Not supported: the exported graph has one input size and one disparity range (its metadata)."""
        raise BackendConfigError(
            f"the onnx backend cannot compute a window (roi {roi!r}, d_min {d_min!r}, d_range {d_range!r}): its graph "
            f"was exported for one {self.height}×{self.width} input and range {self.max_disparity}; "
            "use the sgbm or emcstereo backend for windowed disparity"
        )


def make_onnx_backend(
    weights: str | os.PathLike[str] | None, max_disp: int, device: str, precision: str
) -> OnnxBackend:
    """`make_backend("onnx", …)`: `weights` is the exported .onnx file, whose range `max_disp` must match; CPU fp32."""
    if weights is None:
        raise BackendConfigError("the onnx backend needs weights=PATH of a model written by `emcstereo export --onnx`")
    if device != "cpu" or precision != "fp32":
        raise BackendConfigError(
            f"the onnx backend runs on cpu in fp32 only, got device={device!r} precision={precision!r}"
        )
    backend = OnnxBackend(weights)
    if backend.max_disparity != max_disp:
        raise BackendConfigError(
            f"ONNX model {weights} was exported for max_disp {backend.max_disparity}, not {max_disp}; "
            "pass that max_disp or export again"
        )
    return backend
