"""The geometric segmenter: thin elongated structure in range is a branch, thick is trunk, green is leaf."""

from __future__ import annotations

import numpy as np
import pytest
from branch_geometry_fixtures import GEOMETRY, Cylinder, ray_cast, unit

from branchrange.core.masks import DEFAULT_TRUNK_ID
from branchrange.core.segmentation.segmenter import (
    GeometricSegmenter,
    GeometricSegmenterConfig,
    Segmenter,
    SegmenterConfigError,
)

TRUNK = Cylinder(np.array([-0.35, -1.0, 1.5]), unit([0, 1, 0]), 2.0, 0.08)
BRANCH_A = Cylinder(np.array([-0.28, 0.1, 1.46]), unit([1, -0.3, -0.3]), 0.5, 0.015)
BRANCH_B = Cylinder(np.array([-0.28, -0.2, 1.48]), unit([1, 0.4, 0.2]), 0.4, 0.01)
GREY = np.full((240, 320, 3), 120, np.uint8)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def best_match(masks, truth: np.ndarray) -> float:
    return max(iou(masks.branch(i), truth) for i in masks.branch_ids())


@pytest.fixture(scope="module")
def tree():
    return ray_cast(320, 240, GEOMETRY, {1: [BRANCH_A], 2: [BRANCH_B], 100: [TRUNK]})


def test_geometric_segmenter_keeps_the_segmenter_interface():
    assert isinstance(GeometricSegmenter(), Segmenter)


def test_two_branches_are_separated_from_the_trunk(tree):
    masks = GeometricSegmenter().segment(GREY, tree.disparity, GEOMETRY)
    assert len(masks.branch_ids()) == 2
    assert best_match(masks, tree.labels == 1) > 0.85
    assert best_match(masks, tree.labels == 2) > 0.85
    trunk = masks.trunk()
    assert masks.trunk_id == DEFAULT_TRUNK_ID and trunk is not None
    assert iou(trunk, tree.labels == 100) > 0.9


def test_a_branch_in_front_of_the_trunk_is_cut_free_by_the_depth_edge():
    crossing = Cylinder(np.array([-0.6, 0.0, 1.1]), unit([1, 0.05, 0]), 0.6, 0.012)
    scene = ray_cast(320, 240, GEOMETRY, {1: [crossing], 100: [TRUNK]})
    masks = GeometricSegmenter().segment(GREY, scene.disparity, GEOMETRY)
    assert len(masks.branch_ids()) == 1
    assert best_match(masks, scene.labels == 1) > 0.85


def test_structure_outside_the_working_range_is_ignored(tree):
    masks = GeometricSegmenter(GeometricSegmenterConfig(max_range_m=1.2)).segment(GREY, tree.disparity, GEOMETRY)
    assert masks.branch_ids() == [] and masks.trunk() is None


def test_green_pixels_are_leaves_not_branches(tree):
    green = GREY.copy()
    green[tree.labels == 2] = (40, 160, 30)
    masks = GeometricSegmenter().segment(green, tree.disparity, GEOMETRY)
    assert len(masks.branch_ids()) == 1 and best_match(masks, tree.labels == 1) > 0.85
    off = GeometricSegmenter(GeometricSegmenterConfig(excess_green=-1)).segment(green, tree.disparity, GEOMETRY)
    assert len(off.branch_ids()) == 2


def test_compact_blobs_are_not_branches():
    blob = Cylinder(np.array([0.0, -0.05, 1.2]), unit([0, 1, 0]), 0.1, 0.05)  # short and thick: foliage clump
    scene = ray_cast(320, 240, GEOMETRY, {1: [blob]})
    assert GeometricSegmenter().segment(GREY, scene.disparity, GEOMETRY).branch_ids() == []


def test_low_stereo_confidence_counts_as_no_depth(tree):
    confidence = np.ones_like(tree.disparity)
    confidence[tree.labels == 1] = 0.0
    masks = GeometricSegmenter().segment(GREY, tree.disparity, GEOMETRY, confidence)
    assert len(masks.branch_ids()) == 1 and best_match(masks, tree.labels == 2) > 0.85


def test_size_mismatch_and_bad_config_are_named():
    with pytest.raises(ValueError, match="differ in size"):
        GeometricSegmenter().segment(GREY, np.zeros((10, 10), np.float32), GEOMETRY)
    with pytest.raises(SegmenterConfigError, match=r"segmenter\.geometric\.max_range_m = 1\.0: expected > min_range_m"):
        GeometricSegmenterConfig(min_range_m=2.0, max_range_m=1.0)
