"""The structure segmenter on exact ray-cast scenes: trunk, forks, crossings, a ground plane."""

from __future__ import annotations

import numpy as np
import pytest
from branch_geometry_fixtures import GEOMETRY, Cylinder, ray_cast, unit

from branchrange.core.masks import DEFAULT_TRUNK_ID
from branchrange.core.segmentation.choose import make_segmenter
from branchrange.core.segmentation.segmenter import Segmenter, SegmenterConfigError
from branchrange.core.segmentation.structure import StructureSegmenter, StructureSegmenterConfig, ridge_pixels

TRUNK = Cylinder(np.array([-0.35, -1.0, 1.5]), unit([0, 1, 0]), 2.0, 0.08)
BRANCH_A = Cylinder(np.array([-0.28, 0.1, 1.46]), unit([1, -0.3, -0.3]), 0.5, 0.015)
BRANCH_B = Cylinder(np.array([-0.28, -0.2, 1.48]), unit([1, 0.4, 0.2]), 0.4, 0.01)
GROUND_BELOW_M = 0.35  # a ground plane this far below the camera


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def best_match(masks, truth: np.ndarray) -> float:
    return max((iou(masks.branch(i), truth) for i in masks.branch_ids()), default=0.0)


def picture(labels: np.ndarray, seed: int = 0) -> np.ndarray:
    """RGB: mid-grey noise texture (background), dark bark where `labels` > 0."""
    rng = np.random.default_rng(seed)
    image = rng.integers(150, 170, labels.shape + (1,)).repeat(3, axis=2).astype(np.uint8)
    image[labels > 0] = (70, 60, 50)
    return image


def with_ground(scene) -> tuple[np.ndarray, np.ndarray]:
    """The scene's disparity and labels over a ground plane (y = GROUND_BELOW_M, label 0, nearest wins)."""
    rows = np.arange(scene.disparity.shape[0], dtype=np.float64)[:, None] - GEOMETRY.cy
    ground = np.where(rows > 0, GEOMETRY.baseline_m * rows / GROUND_BELOW_M, 0.0) * np.ones_like(scene.disparity)
    disparity = np.maximum(scene.disparity, ground).astype(np.float32)
    labels = np.where(scene.disparity >= ground, scene.labels, 0)
    return disparity, labels


@pytest.fixture(scope="module")
def tree():
    return ray_cast(320, 240, GEOMETRY, {1: [BRANCH_A], 2: [BRANCH_B], 100: [TRUNK]})


def test_structure_segmenter_is_a_segmenter_and_has_a_name():
    segmenter = make_segmenter("structure")
    assert isinstance(segmenter, Segmenter) and isinstance(segmenter, StructureSegmenter)
    assert segmenter.name == "structure"


def test_two_branches_and_the_trunk(tree):
    masks = StructureSegmenter().segment(picture(tree.labels), tree.disparity, GEOMETRY)
    assert len(masks.branch_ids()) == 2
    assert best_match(masks, tree.labels == 1) > 0.6 and best_match(masks, tree.labels == 2) > 0.6
    assert masks.trunk_id == DEFAULT_TRUNK_ID and iou(masks.trunk(), tree.labels == 100) > 0.8


def test_a_fork_at_one_depth_becomes_two_instances():
    """Two stems from one point on the trunk, 50° apart, the same depth: one component, two lines."""
    base = np.array([-0.27, 0.0, 1.45])
    arms = {
        1: [Cylinder(base, unit([1, -0.45, 0]), 0.45, 0.012)],
        2: [Cylinder(base, unit([1, 0.45, 0]), 0.45, 0.012)],
        100: [TRUNK],
    }
    scene = ray_cast(320, 240, GEOMETRY, arms)
    masks = StructureSegmenter().segment(picture(scene.labels), scene.disparity, GEOMETRY)
    assert len(masks.branch_ids()) == 2
    assert best_match(masks, scene.labels == 1) > 0.5 and best_match(masks, scene.labels == 2) > 0.5


def test_crossing_stems_are_separate_instances():
    """Stem 2 crosses in front of stem 1 (a depth jump): two instances, not one merged X."""
    one = Cylinder(np.array([-0.27, -0.25, 1.5]), unit([1, 0.6, 0]), 0.55, 0.012)
    two = Cylinder(np.array([-0.27, 0.25, 1.35]), unit([1, -0.6, 0]), 0.5, 0.012)
    scene = ray_cast(320, 240, GEOMETRY, {1: [one], 2: [two], 100: [TRUNK]})
    masks = StructureSegmenter().segment(picture(scene.labels), scene.disparity, GEOMETRY)
    assert len(masks.branch_ids()) >= 2
    assert best_match(masks, scene.labels == 1) > 0.3 and best_match(masks, scene.labels == 2) > 0.5


def test_the_ground_plane_is_not_a_branch_and_not_the_trunk(tree):
    disparity, labels = with_ground(tree)
    masks = StructureSegmenter().segment(picture(labels), disparity, GEOMETRY)
    ground = (labels == 0) & (disparity > 0)
    for i in masks.branch_ids():
        assert (masks.branch(i) & ground).sum() < 0.2 * masks.branch(i).sum()
    assert masks.trunk() is not None and (masks.trunk() & ground).sum() < 0.1 * masks.trunk().sum()
    assert best_match(masks, labels == 1) > 0.5


def test_a_loose_stem_away_from_the_trunk_is_dropped_unless_asked(tree):
    loose = Cylinder(np.array([0.2, 0.25, 1.45]), unit([1, 0.1, 0]), 0.2, 0.012)  # 55 cm from the trunk
    scene = ray_cast(320, 240, GEOMETRY, {1: [BRANCH_A], 3: [loose], 100: [TRUNK]})
    image = picture(scene.labels)
    kept = StructureSegmenter().segment(image, scene.disparity, GEOMETRY)
    assert len(kept.branch_ids()) == 1 and best_match(kept, scene.labels == 1) > 0.6
    every = StructureSegmenter(StructureSegmenterConfig(max_trunk_gap_m=0)).segment(image, scene.disparity, GEOMETRY)
    assert len(every.branch_ids()) == 2


def test_ridges_follow_the_image_not_the_disparity():
    image = np.full((60, 80, 3), 160, np.uint8)
    image[28:32, 10:70] = 40  # a 4 px dark stem
    ridge = ridge_pixels(image, (1.0, 2.5), 8.0)
    assert ridge[28:32, 20:60].mean() > 0.9 and not ridge[:15].any() and not ridge[45:].any()


def test_bad_settings_name_the_key():
    with pytest.raises(SegmenterConfigError, match="segmenter.structure.plane_min_share = 0"):
        StructureSegmenterConfig(plane_min_share=0)
    with pytest.raises(ValueError, match="differ in size"):
        StructureSegmenter().segment(np.zeros((10, 10, 3), np.uint8), np.zeros((5, 5), np.float32), GEOMETRY)
