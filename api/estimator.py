"""The narrow interface the routes need (`Estimator`) and its implementation over the pipeline.

Routes hand over decoded RGB arrays and a `CameraSpec`; an estimator returns the `branchrange/v1`
result or the disparity. Keeping routes to this protocol lets them be tested with any real
implementation and keeps FastAPI out of the pipeline.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from branchrange.core.frame_result import FrameResult
from branchrange.core.pipeline import Pipeline, PipelineConfig
from stereo.backends import WEIGHTED_BACKENDS


@dataclass(frozen=True)
class CameraSpec:
    """How to get metres from pixels: a `camera.StereoCalibration` (raw or rectified pair), or
    `focal_px` (pixels at the uploaded resolution) + `baseline_m` (metres) of a rectified pair."""

    calibration: Any = None
    focal_px: float | None = None
    baseline_m: float | None = None


class Estimator(Protocol):
    """What the API calls: one stereo pair in, a result or a disparity out (blocking; run off-loop)."""

    def estimate(
        self,
        left: np.ndarray,
        right: np.ndarray,
        mask: np.ndarray | None,
        camera: CameraSpec,
        *,
        backend: str | None = None,
        max_disp: int | None = None,
        segmenter: str | None = None,
    ) -> FrameResult:
        """`branchrange/v1` result for RGB `uint8 H×W×3` images and an optional instance mask `H×W`;
        `segmenter` 'learned' / 'structure' / 'geometric' asks for a built-in segmenter instead of the
        server's configured one."""
        ...

    def disparity(
        self,
        left: np.ndarray,
        right: np.ndarray,
        camera: CameraSpec,
        *,
        backend: str | None = None,
        max_disp: int | None = None,
    ) -> np.ndarray:
        """Disparity `float32 H×W` (pixels, rectified left view) of the pair."""
        ...


class PipelineEstimator:
    """`Estimator` over `branchrange.core.pipeline.Pipeline`: one pipeline per request (each request is
    its own camera; no tracking across requests), stereo backends built once and reused; every
    pair's rectification is checked (`pair_check` in the result, 422 when refused)."""

    def __init__(self, config: PipelineConfig | None = None):
        config = config or PipelineConfig()
        self.config = replace(config, cutpoints=replace(config.cutpoints, tracking=False), check_pair=True)
        self._backends: dict[tuple[str, int], Any] = {}
        self._segmenters: dict[str, Any] = {}  # by name: an onnx model is loaded once, not per request
        self._lock = threading.Lock()  # backends are shared; one inference at a time uses them

    @property
    def backend_name(self) -> str:
        """The default backend's name, for /health."""
        return self.config.stereo.backend

    def _settings(self, backend: str | None, max_disp: int | None) -> PipelineConfig:
        """The configuration with a request's backend and max_disp in place of the defaults."""
        stereo = self.config.stereo
        return replace(
            self.config, stereo=replace(stereo, backend=backend or stereo.backend, max_disp=max_disp or stereo.max_disp)
        )

    def backend(self, backend: str | None = None, max_disp: int | None = None) -> Any:
        """The stereo backend for these options (default: the configured one), built on first use and
        kept. ValueError when it cannot be built; `branchrange serve` builds the default one at start,
        so a bad [stereo] section fails before the service listens."""
        name = backend or self.config.stereo.backend
        if name in WEIGHTED_BACKENDS and not self.config.stereo.weights:
            raise ValueError(
                f"backend {name!r} has no weights on this server (stereo.weights); "
                "an untrained network would give meaningless cut points"
            )
        cfg = self._settings(backend, max_disp).stereo
        key = (cfg.backend, cfg.max_disp)
        if key not in self._backends:
            self._backends[key] = cfg.build_backend()
        return self._backends[key]

    def segmenter(self, name: str | None = None) -> Any:
        """The segmenter `name` ('learned', 'structure', 'geometric'; default: the configured one), built on
        first use and kept."""
        name = name or self.config.segmenter.model
        if name not in self._segmenters:
            self._segmenters[name] = self.config.segmenter.build(name)
        return self._segmenters[name]

    def _pipeline(
        self, camera: CameraSpec, backend: str | None, max_disp: int | None, segmenter: str | None = None
    ) -> Pipeline:
        stereo = self.backend(backend, max_disp)  # first: its message says why a backend cannot serve
        return Pipeline(
            self._settings(backend, max_disp),
            calibration=camera.calibration,
            focal_px=camera.focal_px,
            baseline_m=camera.baseline_m,
            backend=stereo,
            segmenter=self.segmenter(segmenter),
        )

    def estimate(
        self,
        left: np.ndarray,
        right: np.ndarray,
        mask: np.ndarray | None,
        camera: CameraSpec,
        *,
        backend: str | None = None,
        max_disp: int | None = None,
        segmenter: str | None = None,
    ) -> FrameResult:
        """See `Estimator.estimate`; input errors are the pipeline's ValueErrors."""
        with self._lock:
            return self._pipeline(camera, backend, max_disp, segmenter).process(left, right, mask)

    def disparity(
        self,
        left: np.ndarray,
        right: np.ndarray,
        camera: CameraSpec,
        *,
        backend: str | None = None,
        max_disp: int | None = None,
    ) -> np.ndarray:
        """See `Estimator.disparity`: rectified when the calibration is raw, then the backend (which
        checks the pair, `stereo.backends.validate_pair`, as the route did)."""
        with self._lock:
            pipeline = self._pipeline(camera, backend, max_disp)
            pipeline.geometry_for(left.shape[1], left.shape[0])  # the calibration must fit the size
            if pipeline.rectifier is not None:
                left, right = pipeline.rectifier.rectify(left, right)
            return pipeline.backend.compute(left, right).disparity
