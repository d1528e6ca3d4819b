"""The learned segmenter's out-of-distribution signal: statistic, reference, reading, result field and warning."""

from __future__ import annotations

import json
import logging
import math
import shutil

import numpy as np
import pytest

from branchrange.core.frame_result import FrameResult, json_schema
from branchrange.core.geometry import StereoGeometry
from branchrange.core.pipeline import Pipeline, untracked_whole_frame
from branchrange.core.segmentation.learned import SHIPPED_MODELS, LearnedSegmenter, LearnedSegmenterConfig
from branchrange.core.segmentation.onnx_model import OnnxSegmenterError
from branchrange.core.segmentation.ood import (
    OOD_KEY,
    OodReading,
    OodReference,
    OodReferenceError,
    OodWarnings,
    fitted_reference,
    frame_statistic,
    reference_in,
)
from branchrange.learning.samples import evaluation_scene


@pytest.fixture(scope="module")
def scenes() -> dict[str, dict]:
    """One held-out scene of the training domain and one of the shifted orchard domain (640×360, SGBM)."""
    return {"park": evaluation_scene(50_001, None), "orchard": evaluation_scene(80_000, None, domain="orchard")}


def test_the_shipped_models_carry_a_reference_that_reads_back():
    for model in SHIPPED_MODELS.values():
        meta = json.loads(model.with_suffix(".json").read_text(encoding="utf-8"))
        reference = reference_in(meta)
        assert reference is not None and reference.frames >= 100
        again = OodReference.from_json_dict(json.loads(json.dumps(reference.to_json_dict())))
        assert again.reading(reference.threshold + 0.1) == reference.reading(reference.threshold + 0.1)
        assert reference.reading(reference.threshold + 0.1).flagged
        assert not reference.reading(reference.mean).flagged


def test_a_shifted_domain_frame_reads_as_unknown_and_a_training_domain_frame_does_not(scenes):
    for precision in SHIPPED_MODELS:
        segmenter = LearnedSegmenter(LearnedSegmenterConfig(precision=precision))
        readings = {}
        for domain, scene in scenes.items():
            masks = segmenter.segment(scene["left"], scene["sgbm"], _geometry(scene))
            assert masks.ood is not None
            readings[domain] = masks.ood
        assert readings["orchard"].z > readings["park"].z + 1.5, (precision, readings)
        assert readings["orchard"].flagged and not readings["park"].flagged, (precision, readings)


def test_the_result_carries_the_reading_and_the_schema_describes_it(scenes):
    assert "segmenter_ood" in json_schema()["properties"]
    scene = scenes["orchard"]
    f, b, cx, cy = (float(v) for v in scene["camera"])
    pipeline = Pipeline(untracked_whole_frame(), focal_px=f, baseline_m=b, principal_point=(cx, cy))
    result = pipeline.process_disparity(scene["left"], scene["sgbm"], scene["sgbm_conf"], backend="sgbm")
    assert result.segmenter_ood is not None and result.segmenter_ood.flagged
    assert 0.0 <= result.segmenter_ood.score <= 1.0
    written = result.to_json_dict()
    assert written["segmenter_ood"]["flagged"] is True
    assert FrameResult.from_json_dict(written).segmenter_ood == result.segmenter_ood


def test_a_segmenter_with_the_signal_off_or_without_a_reference_reports_none(scenes, tmp_path):
    scene = scenes["park"]
    off = LearnedSegmenter(LearnedSegmenterConfig(ood=False))
    assert off.segment(scene["left"], scene["sgbm"], _geometry(scene)).ood is None
    model = tmp_path / "branchnet.onnx"
    shutil.copy(SHIPPED_MODELS["fp32"], model)
    meta = json.loads(SHIPPED_MODELS["fp32"].with_suffix(".json").read_text(encoding="utf-8"))
    meta.pop(OOD_KEY)
    model.with_suffix(".json").write_text(json.dumps(meta), encoding="utf-8")
    assert (
        LearnedSegmenter(LearnedSegmenterConfig(model=str(model)))
        .segment(scene["left"], scene["sgbm"], _geometry(scene))
        .ood
        is None
    )


def test_a_damaged_reference_is_refused_with_a_clear_message(tmp_path):
    model = tmp_path / "branchnet.onnx"
    shutil.copy(SHIPPED_MODELS["fp32"], model)
    meta = json.loads(SHIPPED_MODELS["fp32"].with_suffix(".json").read_text(encoding="utf-8"))
    meta[OOD_KEY] = {**meta[OOD_KEY], "statistic": "something_else"}
    model.with_suffix(".json").write_text(json.dumps(meta), encoding="utf-8")
    with pytest.raises(OnnxSegmenterError, match="measure it again"):
        LearnedSegmenter(LearnedSegmenterConfig(model=str(model)))
    for bad in ([1, 2], {**meta[OOD_KEY], "statistic": meta[OOD_KEY]["statistic"], "std": 0}):
        with pytest.raises(OodReferenceError):
            OodReference.from_json_dict(bad)


def test_the_statistic_counts_hesitant_background_away_from_edges_only():
    logits = np.zeros((3, 64, 64), np.float32)
    logits[0] = 5.0  # sure background everywhere
    sure = frame_statistic(logits)
    logits[1, 20:40, 20:40] = 10.0  # a sure trunk: its edges are not hesitation
    logits[:, 20:40, 40] = 5.0  # a hesitant column along its edge
    assert frame_statistic(logits) == pytest.approx(sure)
    logits[2, 0:10, 0:64] = 4.5  # open background the network half calls branch
    assert frame_statistic(logits) > sure + 1.0


def test_a_reference_fitted_on_frames_flags_about_one_in_a_hundred():
    rng = np.random.default_rng(0)
    reference = fitted_reference(rng.normal(-6.0, 0.4, 900), "test")
    assert reference.mean == pytest.approx(-6.0, abs=0.05) and reference.std == pytest.approx(0.4, abs=0.05)
    flagged = np.mean([reference.reading(v).flagged for v in rng.normal(-6.0, 0.4, 2000)])
    assert 0.0 < flagged < 0.03
    with pytest.raises(ValueError, match="at least"):
        fitted_reference([1.0, 2.0], "too few")


def test_flagged_frames_are_warned_about_once_per_interval(caplog):
    now = [0.0]
    warnings = OodWarnings(interval_s=30.0, clock=lambda: now[0])
    flagged, fine = OodReading(1.0, 4.0, True), OodReading(0.5, 0.0, False)
    with caplog.at_level(logging.WARNING, logger="branchrange.core.segmentation.ood"):
        assert not warnings.note(fine) and not warnings.note(None)
        assert warnings.note(flagged)
        for t in (1.0, 10.0, 29.0):
            now[0] = t
            assert not warnings.note(flagged)
        now[0] = 31.0
        assert warnings.note(flagged)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and "does not look like it knows this scene" in lines[0]
    assert "4 of the last 4 frames" in lines[1]  # the three held back and this one


def _geometry(scene: dict) -> StereoGeometry:
    """The scene's `StereoGeometry`."""
    f, b, cx, cy = (float(v) for v in scene["camera"])
    return StereoGeometry(focal_px=f, baseline_m=b, cx=cx, cy=cy)


def test_reading_of_a_value_beyond_every_held_out_frame_scores_one():
    reference = fitted_reference(np.linspace(-7, -5, 30), "line")
    assert reference.reading(0.0).score == 1.0 and math.isfinite(reference.reading(0.0).z)


def test_a_models_reference_is_measured_on_frames_stored_in_its_json_and_read_at_load(tmp_path):
    from branchrange.learning.ood_reference import model_reference, store_reference

    model = tmp_path / "branchnet.onnx"
    shutil.copy(SHIPPED_MODELS["fp32"], model)
    meta = json.loads(SHIPPED_MODELS["fp32"].with_suffix(".json").read_text(encoding="utf-8"))
    meta.pop(OOD_KEY)
    model.with_suffix(".json").write_text(json.dumps(meta), encoding="utf-8")
    rng = np.random.default_rng(3)
    frames = [
        (rng.integers(0, 256, (96, 160, 3), dtype=np.uint8), rng.uniform(1, 20, (96, 160)).astype(np.float32))
        for _ in range(12)
    ]
    reference = model_reference(model, frames, "noise frames")
    assert reference.frames == 12 and reference.held_out.size == 4 and reference.domain == "noise frames"
    store_reference(model, reference)
    stored = json.loads(model.with_suffix(".json").read_text(encoding="utf-8"))
    assert stored["onnx_sha256"] == meta["onnx_sha256"] and "confidence_calibrations" in stored  # the rest kept
    loaded = LearnedSegmenter(LearnedSegmenterConfig(model=str(model))).ood_reference
    assert loaded is not None and loaded.threshold == pytest.approx(reference.threshold, abs=1e-4)


def test_ood_only_refuses_other_modes_and_a_missing_model(tmp_path, capsys):
    from branchrange.cli import main

    argv = ["train-segmenter", "--out", str(tmp_path), "--ood-only"]
    assert main(argv) == 2
    assert "does not exist (train first)" in capsys.readouterr().err
    (tmp_path / "branchnet.onnx").write_bytes(b"a model")
    assert main([*argv, "--no-calibrate"]) == 2
    assert "--ood-only excludes" in capsys.readouterr().err
    assert main([*argv, "--int8"]) == 2  # no int8 copy beside it
    assert "branchnet_int8.onnx does not exist" in capsys.readouterr().err
