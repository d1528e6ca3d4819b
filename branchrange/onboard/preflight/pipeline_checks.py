"""The pipeline checks: every model the configuration names loads and has its recorded SHA-256; a frame of the
camera goes through the whole pipeline within the latency budget.

Models: the stereo backend (`[stereo]`; EMCStereo weights named as a registered release are compared with
the release's SHA-256 even where `stereo.verify_weights` is off) and the segmenter (`[segmenter]`; the
learned segmenter refuses a model whose SHA-256 differs from the one its metadata or bundle manifest
records). Latency: the first frame warms the pipeline up (lazily built parts), then every further frame
the camera check read is timed through stereo, segmentation, cut points and tracking. Their median (as
in the daemon's speed report after its first frames) must be within `mavlink.max_result_age_s`, the age
beyond which the daemon sends "no target": the daemon's capture → publish age adds its queues to this,
so a pipeline over the budget here is over it in flight too.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from branchrange.config.loader import pipeline_config
from branchrange.core.frame_results import process_frame
from branchrange.core.pipeline import Pipeline
from branchrange.core.segmentation.learned import verified_metadata
from branchrange.core.settings_check import check_calibration
from branchrange.onboard.preflight.camera_checks import CameraSample
from branchrange.onboard.preflight.report import CheckResult
from stereo.weights import cached_sha256, registered_as

if TYPE_CHECKING:
    from branchrange.config.loader import Config

MODELS, LATENCY = "models", "pipeline latency"
MODEL_FIX = (
    "copy the model files again from the release (a whole bundle folder, not single files); their SHA-256 must match"
)


def check_models(cfg: Config) -> tuple[CheckResult, tuple[Any, Any] | None]:
    """The models check, and the (stereo backend, segmenter) it loaded (None when one failed)."""
    weights = Path(cfg.stereo.weights) if cfg.stereo.weights else None
    release = registered_as(weights) if weights is not None else None
    if weights is not None and weights.is_file() and release is not None and cached_sha256(weights) != release.sha256:
        found = f"stereo weights {weights}: SHA-256 {cached_sha256(weights)}, release {release.name}: {release.sha256}"
        return CheckResult.failed(MODELS, found, MODEL_FIX), None
    try:
        backend = cfg.stereo.build_backend()
        segmenter = cfg.segmenter.build()
    except (ValueError, OSError, RuntimeError) as exc:  # a checkpoint, bundle or ONNX file that cannot be used
        return CheckResult.failed(MODELS, str(exc), MODEL_FIX), None
    found = f"{_stereo_found(cfg, weights, release is not None)}; {_segmenter_found(segmenter)}"
    return CheckResult.passed(MODELS, found), (backend, segmenter)


def _stereo_found(cfg: Config, weights: Path | None, registered: bool) -> str:
    if weights is None:
        return f"stereo {cfg.stereo.backend} (no weights file)"
    digest = cached_sha256(weights)[:16]
    checked = "the release's" if registered else "no release's to compare with: a local checkpoint"
    return f"stereo {cfg.stereo.backend} {weights.name} SHA-256 {digest}… ({checked})"


def _segmenter_found(segmenter: Any) -> str:
    model_path = getattr(segmenter, "model_path", None)
    if model_path is None:
        return f"segmenter {segmenter.name} (no SHA-256 recorded for it to check)"
    recorded = verified_metadata(model_path).get("onnx_sha256")
    if not recorded:
        return f"segmenter {segmenter.name} {model_path.name} (no SHA-256 recorded beside it)"
    return f"segmenter {segmenter.name} {model_path.name} SHA-256 {recorded[:16]}… (as recorded)"


def check_latency(cfg: Config, sample: CameraSample, models: tuple[Any, Any]) -> CheckResult:
    """Time the camera's frames through the pipeline (the first as a warm-up) against `mavlink.max_result_age_s`."""
    budget_s = cfg.mavlink.max_result_age_s
    backend, segmenter = models
    if sample.calibration is None:
        return CheckResult.skipped(LATENCY, "no calibration to run the pipeline with")
    try:
        check_calibration(sample.calibration, sample.frames[0].size, "camera.calibration")
        pipeline = Pipeline(pipeline_config(cfg), calibration=sample.calibration, backend=backend, segmenter=segmenter)
        process_frame(pipeline, sample.frames[0])
        seconds = []
        for frame in sample.frames[1:] or sample.frames:
            start = time.perf_counter()
            process_frame(pipeline, frame)
            seconds.append(time.perf_counter() - start)
    except ValueError as exc:  # the calibration out of range, or a frame the pipeline refuses
        return CheckResult.failed(LATENCY, str(exc), "check camera.calibration and camera.source, then run again")
    typical, worst = statistics.median(seconds), max(seconds)
    found = f"median {typical * 1000:.0f} ms (worst {worst * 1000:.0f} ms) of {len(seconds)} frame(s), "
    found += f"budget mavlink.max_result_age_s = {budget_s * 1000:.0f} ms"
    if typical <= budget_s:
        return CheckResult.passed(LATENCY, found)
    if cfg.stereo.mode != "roi":
        fix = 'set stereo.mode = "roi" (only the branches matched at full resolution)'
    else:
        fix = "lower stereo.max_disp to the working range or roi.coarse_width, or run deploy/onboard_cpu.toml on a CPU"
    return CheckResult.failed(LATENCY, found, fix + " (see docs/performance.md)")
