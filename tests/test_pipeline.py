"""The per-frame pipeline against the synthetic generator's exact truth, its schema and its bad inputs."""

from __future__ import annotations

import json

import jsonschema
import numpy as np
import pytest

from branchrange.core.cutpoints import CutPointConfig
from branchrange.core.frame_result import SCHEMA_PATH, Frame
from branchrange.core.masks import MaskError, masks_from_array
from branchrange.core.pipeline import Pipeline, PipelineConfig, PipelineInputError, StereoConfig
from branchrange.core.segmentation.choose import SegmenterConfig
from branchrange.core.segmentation.segmenter import Segmenter
from camera import StereoCalibration
from stereo.synth import SynthCamera, render_scene

SEED = 6


@pytest.fixture(scope="module")
def scene():
    return render_scene(SEED, SynthCamera.zed_mini(640, 360))


@pytest.fixture(scope="module")
def validator():
    schema = json.loads(SCHEMA_PATH.read_text(encoding="utf-8"))
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def pipeline_for(scene, **config) -> Pipeline:
    return Pipeline(PipelineConfig(**config), focal_px=scene.camera.focal_px, baseline_m=scene.camera.baseline_m)


def visible_truth(scene):
    return [b for b in scene.branches if b.cut_visible and b.mask_pixels >= 30]


def errors_by_truth(result, scene):
    estimates = {b.mask_id: np.array(b.cut_point_m) for b in result.branches}
    return {
        b.id: float(np.linalg.norm(estimates[b.id] - np.array(b.cut_point_m)))
        for b in visible_truth(scene)
        if b.id in estimates
    }


@pytest.fixture(scope="module")
def sgbm_result(scene):
    return pipeline_for(scene, stereo=StereoConfig(mode="full", max_disp=128)).process(
        scene.left, scene.right, mask=scene.instance_mask, index=7, timestamp_ns=123
    )


def test_sgbm_result_matches_the_schema_with_per_stage_timing(sgbm_result, validator):
    validator.validate(sgbm_result.to_json_dict())
    assert sgbm_result.schema == "branchrange/v1"
    assert sgbm_result.frame == Frame(index=7, timestamp_ns=123, width=640, height=360)
    assert sgbm_result.stereo.backend == "sgbm" and sgbm_result.stereo.max_disparity == 128
    timing = sgbm_result.timing_ms
    assert timing["stereo"] > 0 and timing["cutpoints"] > 0
    assert timing["total"] >= timing["stereo"] + timing["cutpoints"]


def test_sgbm_cut_points_land_near_the_truth(sgbm_result, scene):
    errors = errors_by_truth(sgbm_result, scene)
    truth = visible_truth(scene)
    assert len(errors) >= len(truth) - 1
    within_5cm = sum(e < 0.05 for e in errors.values())
    assert within_5cm >= 0.7 * len(truth), errors


def test_target_is_the_nearest_branch_with_distance_weighted_by_confidence(sgbm_result):
    branches = sgbm_result.branches
    confident = [b for b in branches if b.confidence >= 0.3]
    assert confident
    best = min(confident, key=lambda b: b.distance_m / b.confidence)
    assert sgbm_result.target_id == best.id and sgbm_result.target == best


def test_ground_truth_disparity_and_masks_give_sub_centimetre_cut_points(scene, validator):
    result = pipeline_for(scene).process_disparity(scene.left, scene.disparity, mask=scene.instance_mask)
    validator.validate(result.to_json_dict())
    errors = errors_by_truth(result, scene)
    assert len(errors) == len(visible_truth(scene))
    assert np.median(list(errors.values())) < 0.01
    assert max(errors.values()) < 0.05
    for branch in result.branches:
        truth = scene.branches[branch.mask_id - 1]
        assert branch.diameter_m == pytest.approx(2 * truth.radius_at(truth.cut_offset_m), rel=0.35, abs=0.002)
        assert np.dot(branch.axis, truth.direction) > 0.99


def test_built_in_segmenter_finds_branches_without_a_mask(scene, validator):
    result = pipeline_for(scene, segmenter=SegmenterConfig(model="geometric")).process_disparity(
        scene.left, scene.disparity
    )
    validator.validate(result.to_json_dict())
    assert result.masks.source == "geometric"
    found = [
        b
        for b in visible_truth(scene)
        if any(np.linalg.norm(np.array(e.cut_point_m) - b.cut_point_m) < 0.05 for e in result.branches)
    ]
    assert len(found) >= 2


class TruthSegmenter:
    """A plug-in segmenter (as a learned model would be) that returns the scene's own instance mask."""

    name = "truth"

    def __init__(self, instance_mask: np.ndarray) -> None:
        self.instance_mask = instance_mask

    def segment(self, left, disparity, geometry, confidence=None):
        return masks_from_array(self.instance_mask, source=self.name)


def test_a_plugged_in_segmenter_replaces_the_built_in_one(scene):
    plugged = TruthSegmenter(scene.instance_mask)
    assert isinstance(plugged, Segmenter)
    pipeline = Pipeline(
        PipelineConfig(cutpoints=CutPointConfig(tracking=False)),
        focal_px=scene.camera.focal_px,
        baseline_m=scene.camera.baseline_m,
        segmenter=plugged,
    )
    result = pipeline.process_disparity(scene.left, scene.disparity)
    given = pipeline_for(scene, cutpoints=CutPointConfig(tracking=False)).process_disparity(
        scene.left, scene.disparity, mask=scene.instance_mask
    )
    assert result.masks.source == "truth" and result.masks.trunk is True
    assert [b.cut_point_m for b in result.branches] == [b.cut_point_m for b in given.branches]
    assert len(result.branches) == len(visible_truth(scene))


def test_ids_stay_stable_across_frames(scene):
    pipeline = pipeline_for(scene)
    first = pipeline.process_disparity(scene.left, scene.disparity, mask=scene.instance_mask, index=0)
    second = pipeline.process_disparity(scene.left, scene.disparity, mask=scene.instance_mask, index=1)
    assert {b.mask_id: b.id for b in first.branches} == {b.mask_id: b.id for b in second.branches}
    assert first.target_id == second.target_id is not None
    pipeline.reset()
    third = pipeline.process_disparity(scene.left, scene.disparity, mask=scene.instance_mask, index=2)
    assert min(b.id for b in third.branches) > max(b.id for b in second.branches)


def test_raw_calibration_path_rectifies_pair_and_mask(scene):
    """An unrectified calibration that happens to be ideal gives the same cut points as the rectified path."""
    cam = scene.camera
    k = np.array([[cam.focal_px, 0, cam.cx], [0, cam.focal_px, cam.cy], [0, 0, 1.0]])
    raw = StereoCalibration(
        k, np.zeros(5), k, np.zeros(5), np.eye(3), np.array([-cam.baseline_m, 0, 0]), (cam.width, cam.height)
    )
    pipeline = Pipeline(
        PipelineConfig(stereo=StereoConfig(mode="full", max_disp=128), cutpoints=CutPointConfig(tracking=False)),
        calibration=raw,
    )
    assert pipeline.rectifier is not None
    result = pipeline.process(scene.left, scene.right, mask=scene.instance_mask)
    assert result.camera.focal_px == pytest.approx(cam.focal_px, rel=1e-6)
    assert result.camera.baseline_m == pytest.approx(cam.baseline_m, rel=1e-6)
    assert result.masks.instances == len(
        np.unique(scene.instance_mask[(scene.instance_mask > 0) & (scene.instance_mask < 65533)])
    )
    assert sum(e < 0.05 for e in errors_by_truth(result, scene).values()) >= 0.7 * len(visible_truth(scene))


# --- bad input: a specific error, or an empty result that says why; never a crash or a made-up point


def test_mismatched_pair_sizes_are_refused(scene):
    with pytest.raises(PipelineInputError, match="differ in size"):
        pipeline_for(scene).process(scene.left, scene.right[:, :-8])


def test_non_rgb_images_are_refused(scene):
    with pytest.raises(PipelineInputError, match="uint8 H×W×3"):
        pipeline_for(scene).process(scene.left.astype(np.float32), scene.right)


def test_wrong_size_mask_is_refused(scene):
    with pytest.raises(MaskError, match="must match the left image"):
        pipeline_for(scene).process_disparity(scene.left, scene.disparity, mask=scene.instance_mask[:-2])


def test_empty_mask_gives_an_empty_result_with_a_reason(scene, validator):
    result = pipeline_for(scene).process_disparity(
        scene.left, scene.disparity, mask=np.zeros(scene.disparity.shape, np.uint16)
    )
    validator.validate(result.to_json_dict())
    assert result.branches == () and result.target_id is None and result.target is None
    assert "no branch instance" in result.reason


@pytest.mark.parametrize("fill", [0.0, np.nan, np.inf, -5.0])
def test_all_invalid_disparity_gives_an_empty_result_with_a_reason(scene, validator, fill):
    disparity = np.full(scene.disparity.shape, fill, np.float32)
    result = pipeline_for(scene).process_disparity(scene.left, disparity, mask=scene.instance_mask)
    validator.validate(result.to_json_dict())
    assert result.branches == () and result.target_id is None and result.target is None
    assert "no valid disparity" in result.reason


def test_non_finite_disparity_values_are_no_evidence(scene, validator):
    disparity = scene.disparity.copy()
    disparity[scene.instance_mask == 1] = np.nan  # branch 1 loses all its depth
    disparity[::7, ::5] = np.inf
    result = pipeline_for(scene).process_disparity(scene.left, disparity, mask=scene.instance_mask)
    validator.validate(result.to_json_dict())
    assert 1 not in [b.mask_id for b in result.branches]
    assert any(d.mask_id == 1 and "valid depth" in d.reason for d in result.dropped)
    assert all(np.all(np.isfinite(b.cut_point_m)) for b in result.branches)


def test_calibration_for_another_resolution_is_refused(scene):
    cam = scene.camera
    k = np.array([[cam.focal_px, 0, cam.cx], [0, cam.focal_px, cam.cy], [0, 0, 1.0]])
    other = StereoCalibration(k, np.zeros(5), k, np.zeros(5), np.eye(3), np.array([-cam.baseline_m, 0, 0]), (1280, 720))
    with pytest.raises(PipelineInputError, match="1280×720 px images but the frames are 640×360"):
        Pipeline(calibration=other).process(scene.left, scene.right)


def test_missing_camera_description_is_refused():
    with pytest.raises(PipelineInputError, match="focal_px and baseline_m"):
        Pipeline()
