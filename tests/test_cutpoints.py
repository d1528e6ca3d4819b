"""Cut points against exactly ray-cast cylinders: position, axis, diameter, base side, confidence."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from branch_geometry_fixtures import GEOMETRY, TRUNK_LABEL, Cylinder, branch_with_trunk, ray_cast, unit

from branchrange.core.confidence import visible_length_factor
from branchrange.core.cutpoints import (
    BranchEstimate,
    CutPointConfig,
    CutPointConfigError,
    DroppedBranch,
    depth_precision_score,
    estimate_cut_points,
    select_target,
)
from branchrange.core.frame_result import Branch, DroppedInstance
from branchrange.core.geometry import StereoGeometry
from branchrange.core.masks import masks_from_array

OFFSET = CutPointConfig().cut_offset_m


def estimate(scene, trunk_id=TRUNK_LABEL, config=CutPointConfig(), confidence=None, disparity=None):
    masks = masks_from_array(scene.labels, trunk_id=trunk_id, kind="instance")
    d = scene.disparity if disparity is None else disparity
    return estimate_cut_points(masks, d, GEOMETRY, config, confidence=confidence)


@pytest.mark.parametrize("direction", [(1, -0.3, -0.4), (1, 0, 0), (1, 0.5, 0.3), (1, -1, 0), (0.5, -0.2, -1)])
@pytest.mark.parametrize("radius", [0.008, 0.02])
def test_cut_point_within_a_centimetre_on_exact_disparity(direction, radius):
    scene, base, d = branch_with_trunk(direction=direction, radius=radius)
    [b] = estimate(scene).branches
    assert np.linalg.norm(b.cut_point_m - (base + OFFSET * d)) < 0.01
    assert b.axis @ d > np.cos(np.radians(2.0))  # points from base toward the tip
    assert b.diameter_m == pytest.approx(2 * radius, rel=0.1)
    assert b.distance_m == pytest.approx(np.linalg.norm(base + OFFSET * d), abs=0.01)
    assert b.confidence > 0.8


def test_cut_offset_moves_the_cut_along_the_axis():
    scene, base, d = branch_with_trunk()
    near = estimate(scene, config=CutPointConfig(cut_offset_m=0.0)).branches[0]
    far = estimate(scene, config=CutPointConfig(cut_offset_m=0.15)).branches[0]
    np.testing.assert_allclose(far.cut_point_m - near.cut_point_m, 0.15 * far.axis, atol=1e-9)
    assert np.linalg.norm(near.cut_point_m - base) < 0.01
    assert np.linalg.norm(near.base_m - base) < 0.01


def test_pixel_is_the_projection_of_the_cut_point():
    scene, _, _ = branch_with_trunk()
    [b] = estimate(scene).branches
    x, y, z = b.cut_point_m
    assert b.pixel[0] == pytest.approx(GEOMETRY.focal_px * x / z + GEOMETRY.cx)
    assert b.pixel[1] == pytest.approx(GEOMETRY.focal_px * y / z + GEOMETRY.cy)


def test_base_is_the_end_at_the_trunk_even_when_the_tip_is_thicker_in_the_image():
    # a branch growing from the trunk toward the camera: its tip is nearer, so wider in pixels
    scene, base, d = branch_with_trunk(direction=(1.0, 0.0, -0.9), radius=0.02)
    [b] = estimate(scene).branches
    assert b.axis @ d > 0.99
    assert np.linalg.norm(b.base_m - base) < 0.01


def test_without_a_trunk_the_thicker_end_is_the_base():
    start, direction = np.array([-0.3, 0.0, 1.4]), unit([1.0, 0.2, 0.0])
    thick = Cylinder(start, direction, 0.2, 0.025)
    thin = Cylinder(start + 0.2 * direction, direction, 0.25, 0.01)
    scene = ray_cast(320, 240, GEOMETRY, {7: [thick, thin]})
    [b] = estimate(scene, trunk_id=None).branches
    assert b.mask_id == 7
    assert b.axis @ direction > 0.99
    assert np.linalg.norm(b.base_m - start) < 0.02


def test_flipping_which_side_the_trunk_is_on_flips_the_axis():
    scene, _, d = branch_with_trunk(direction=(1, 0, 0))
    # relabel: pretend the trunk sits at the other end by mirroring the image left-right
    mirrored = scene.labels[:, ::-1].copy()
    disparity = scene.disparity[:, ::-1].copy()
    masks = masks_from_array(mirrored, trunk_id=TRUNK_LABEL, kind="instance")
    [b] = estimate_cut_points(masks, disparity, GEOMETRY).branches
    assert b.axis[0] < -0.9  # still points away from the (now right-hand) trunk


def test_silhouette_outliers_do_not_move_the_cut_point():
    scene, base, d = branch_with_trunk(radius=0.015)
    rng = np.random.default_rng(0)
    disparity = scene.disparity.copy()
    rows, cols = np.nonzero(scene.labels == 1)
    pick = rng.random(rows.size) < 0.25  # a quarter of the branch takes the background's disparity
    disparity[rows[pick], cols[pick]] = GEOMETRY.fb / rng.uniform(3.0, 6.0, pick.sum())
    [b] = estimate(scene, disparity=disparity).branches
    assert np.linalg.norm(b.cut_point_m - (base + OFFSET * d)) < 0.012
    clean = estimate(scene).branches[0]
    assert b.confidence < clean.confidence


def test_disparity_noise_lowers_confidence_but_keeps_the_cut_near():
    scene, base, d = branch_with_trunk(radius=0.015)
    rng = np.random.default_rng(1)
    noisy = scene.disparity + rng.normal(0, 0.3, scene.disparity.shape).astype(np.float32) * (scene.disparity > 0)
    [b] = estimate(scene, disparity=noisy).branches
    assert np.linalg.norm(b.cut_point_m - (base + OFFSET * d)) < 0.03


def test_stereo_confidence_scales_the_branch_confidence():
    scene, _, _ = branch_with_trunk()
    sure = estimate(scene, confidence=np.ones_like(scene.disparity)).branches[0]
    unsure = estimate(scene, confidence=np.full_like(scene.disparity, 0.5)).branches[0]
    assert unsure.confidence == pytest.approx(0.5 * sure.confidence, rel=1e-6)


def test_the_depth_precision_at_the_cut_scales_the_confidence():
    scene, _, _ = branch_with_trunk()
    exact = estimate(scene, config=CutPointConfig(cut_disparity_noise_px=0.0)).branches[0]
    matched = estimate(scene, config=CutPointConfig(cut_disparity_noise_px=0.3)).branches[0]
    sigma_z = exact.cut_point_m[2] ** 2 * 0.3 / GEOMETRY.fb  # first-order error of Z = f·B / d
    expected = math.erf(0.05 / (math.sqrt(2.0) * sigma_z))
    assert 0.0 < expected < 0.99  # the fixture's cut point is far enough for the factor to show
    assert matched.confidence == pytest.approx(expected * exact.confidence, rel=1e-6)


def test_a_far_cut_point_or_a_short_baseline_is_less_sure():
    config = CutPointConfig()
    near, far = (depth_precision_score(z, GEOMETRY, config) for z in (1.0, 3.0))
    assert 0.0 < far < near <= 1.0
    wide = StereoGeometry(GEOMETRY.focal_px, 4 * GEOMETRY.baseline_m, GEOMETRY.cx, GEOMETRY.cy)
    assert depth_precision_score(3.0, wide, config) > far
    assert depth_precision_score(3.0, GEOMETRY, CutPointConfig(cut_disparity_noise_px=0.0)) == 1.0
    with pytest.raises(CutPointConfigError, match="cut_tolerance_m"):
        CutPointConfig(cut_tolerance_m=0.0)


def test_all_invalid_disparity_drops_the_branch_with_a_reason():
    scene, _, _ = branch_with_trunk()
    result = estimate(scene, disparity=np.full_like(scene.disparity, np.nan))
    assert result.branches == []
    [dropped] = result.dropped
    assert dropped.mask_id == 1 and "valid depth" in dropped.reason


def test_mostly_missing_depth_is_dropped_not_invented():
    scene, _, _ = branch_with_trunk()
    disparity = scene.disparity.copy()
    rows, cols = np.nonzero(scene.labels == 1)
    keep = np.zeros(rows.size, dtype=bool)
    keep[::12] = True  # ~8 % of the branch keeps its depth
    disparity[rows[~keep], cols[~keep]] = 0.0
    result = estimate(scene, disparity=disparity)
    assert not result.branches and "valid depth" in result.dropped[0].reason


def test_a_tiny_mask_is_dropped():
    labels = np.zeros((240, 320), dtype=np.int32)
    labels[100:102, 100:103] = 1  # 6 pixels
    masks = masks_from_array(labels, kind="instance")
    result = estimate_cut_points(masks, np.full((240, 320), 20.0, np.float32), GEOMETRY)
    assert not result.branches and "fewer than" in result.dropped[0].reason


def test_out_of_range_cut_points_are_dropped():
    scene, _, _ = branch_with_trunk()
    result = estimate(scene, config=CutPointConfig(max_range_m=1.0))
    assert not result.branches and "working range" in result.dropped[0].reason


def test_a_fragment_shorter_than_the_cut_offset_is_dropped_not_extrapolated():
    short, _, _ = branch_with_trunk(length=0.03)  # the cut 5 cm out would lie in the air past its end
    result = estimate(short)
    assert not result.branches and "beyond the visible branch" in result.dropped[0].reason
    assert len(estimate(short, config=CutPointConfig(max_cut_beyond_tip_m=0.05)).branches) == 1
    scene, base, d = branch_with_trunk(length=0.07)  # the cut lies on the branch
    [b] = estimate(scene).branches
    assert np.linalg.norm(b.cut_point_m - (base + OFFSET * d)) < 0.01
    with pytest.raises(CutPointConfigError, match="max_cut_beyond_tip_m"):
        CutPointConfig(max_cut_beyond_tip_m=-0.01)


def test_config_errors_name_the_key():
    with pytest.raises(CutPointConfigError, match=r"cutpoints\.min_points = 1: expected ≥ 3 points"):
        CutPointConfig(min_points=1)
    with pytest.raises(CutPointConfigError, match=r"cutpoints\.max_range_m = 1\.0: expected > min_range_m \(2\.0 m\)"):
        CutPointConfig(min_range_m=2.0, max_range_m=1.0)


def _branch(mask_id, distance, confidence, diameter):
    point = np.array([0.0, 0.0, distance])
    return BranchEstimate(
        mask_id,
        point,
        point,
        np.array([1.0, 0, 0]),
        distance,
        (0.0, 0.0),
        diameter,
        confidence,
        1.0,
        0.0,
        100,
        id=mask_id,
    )


def test_target_selector_policies_and_confidence_floor():
    branches = [
        _branch(1, 1.0, 0.2, 0.02),
        _branch(2, 1.5, 0.9, 0.03),
        _branch(3, 2.0, 0.6, 0.05),
        _branch(4, 1.2, 0.45, 0.02),
    ]
    # default: smallest distance / confidence among those ≥ 0.3 — 1.5/0.9 beats 1.2/0.45 and 2.0/0.6
    assert select_target(branches).mask_id == 2
    assert select_target(branches, "nearest").mask_id == 4  # nearest among those ≥ 0.3
    assert select_target(branches, "nearest", min_confidence=0.1).mask_id == 1
    assert select_target(branches, min_confidence=0.1).mask_id == 2  # 1.0/0.2 = 5 counts as far
    assert select_target(branches, "most_confident").mask_id == 2
    assert select_target(branches, "thickest").mask_id == 3
    assert select_target(branches, min_confidence=0.95) is None
    with pytest.raises(CutPointConfigError, match="farthest"):
        select_target(branches, "farthest")


def test_dropped_and_estimates_serialise_to_plain_json_types():
    scene, _, _ = branch_with_trunk()
    [b] = estimate(scene).branches
    entry = Branch.from_estimate(b).to_json_dict()
    assert set(entry) >= {"id", "cut_point_m", "distance_m", "pixel", "diameter_m", "axis", "base_m", "confidence"}
    assert all(type(v) is float for v in entry["cut_point_m"]) and isinstance(entry["cut_point_m"], list)
    assert entry["distance_m"] == round(b.distance_m, 5) and type(entry["points"]) is int
    assert DroppedInstance.from_dropped(DroppedBranch(3, "why")).to_json_dict() == {"mask_id": 3, "reason": "why"}


@pytest.mark.parametrize("length", [0.12, 0.45])
def test_a_segmenters_visible_length_scale_scores_the_branch_by_how_long_it_is_seen(length):
    """`BranchMasks.visible_length_scale_m` (the learned segmenter's, measured with its calibration): the cut
    point's confidence is scaled by L / (L + scale) of the branch's visible length L — a short piece is more
    often a fragment. A mask file (scale 0, no score) is reported as it is."""
    scene, _, _ = branch_with_trunk(length=length)
    plain = masks_from_array(scene.labels, trunk_id=TRUNK_LABEL, kind="instance")
    assert plain.reported_confidence(1) is None
    [as_is] = estimate_cut_points(plain, scene.disparity, GEOMETRY).branches
    scored = replace(plain, visible_length_scale_m=0.1)
    [by_length] = estimate_cut_points(scored, scene.disparity, GEOMETRY).branches
    np.testing.assert_allclose(by_length.cut_point_m, as_is.cut_point_m)
    # the visible part runs from the trunk's surface to the tip: the cylinder's length, less what the ray cast hides
    ratio = by_length.confidence / as_is.confidence
    assert ratio == pytest.approx(visible_length_factor(length, 0.1), rel=0.08)
    assert visible_length_factor(length, 0.0) == 1.0
    assert visible_length_factor(0.05, 0.1) < visible_length_factor(0.2, 0.1) < visible_length_factor(1.0, 0.1) < 1
