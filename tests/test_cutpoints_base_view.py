"""A branch whose base is not in view gives no cut point: cut by the image border, or hidden at its base."""

from __future__ import annotations

import numpy as np
import pytest
from branch_geometry_fixtures import GEOMETRY, TRUNK_LABEL, Cylinder, branch_with_trunk, ray_cast, unit

from branchrange.core.cutpoints import CutPointConfig, CutPointConfigError, estimate_cut_points
from branchrange.core.masks import masks_from_array

OFFSET = CutPointConfig().cut_offset_m
DIRECTION = unit([0.3, -1.0, 0.0])  # growing up and to the right
OCCLUDER = 9  # rendered for its depth, then relabelled background


def _tapered_branch(start: np.ndarray) -> dict[int, list[Cylinder]]:
    """A branch from `start` (its base, m): thick for 20 cm, then thin, so the thicker end is the base."""
    return {7: [Cylinder(start, DIRECTION, 0.2, 0.025), Cylinder(start + 0.2 * DIRECTION, DIRECTION, 0.25, 0.01)]}


def _estimate(parts: dict[int, list[Cylinder]], config: CutPointConfig = CutPointConfig()):
    scene = ray_cast(320, 240, GEOMETRY, parts)
    labels = scene.labels.copy()
    labels[labels == OCCLUDER] = 0
    masks = masks_from_array(labels, trunk_id=None, kind="instance")
    return estimate_cut_points(masks, scene.disparity, GEOMETRY, config), scene


def test_a_branch_whose_base_the_bottom_edge_cuts_gives_no_cut_point():
    # 1.4 m away the bottom row is at y = 0.335 m: the base at y = 0.40 m lies ~23 px below the image,
    # the true cut point (5 cm up the branch) ~17 px below it
    result, scene = _estimate(_tapered_branch(np.array([-0.1, 0.40, 1.4])))
    assert scene.labels[-1].any(), "the branch must run out of the bottom of the image"
    assert not result.branches
    [dropped] = result.dropped
    assert dropped.mask_id == 7 and "image border cuts the branch at its base" in dropped.reason


def test_the_same_branch_with_its_base_in_view_keeps_its_cut_point():
    start = np.array([-0.1, 0.25, 1.4])
    result, scene = _estimate(_tapered_branch(start))
    assert not scene.labels[-1].any()
    [b] = result.branches
    assert np.linalg.norm(b.cut_point_m - (start + OFFSET * DIRECTION)) < 0.015


def test_a_tip_cut_by_the_border_does_not_matter():
    # base well inside, the thin end runs out of the top of the image
    start = np.array([-0.25, 0.2, 1.0])
    parts = {7: [Cylinder(start, DIRECTION, 0.25, 0.025), Cylinder(start + 0.25 * DIRECTION, DIRECTION, 0.4, 0.012)]}
    result, scene = _estimate(parts)
    assert scene.labels[0].any(), "the branch must run out of the top of the image"
    [b] = result.branches
    assert np.linalg.norm(b.cut_point_m - (start + OFFSET * DIRECTION)) < 0.015


@pytest.mark.parametrize(("occluder_z", "hidden"), [(1.0, True), (1.9, False)])
def test_a_base_hidden_behind_something_nearer_gives_no_cut_point(occluder_z, hidden):
    # a thick horizontal bar across the branch's base: 0.4 m in front of it hides the base; behind it, it is
    # background, and the silhouette's end is the base
    start = np.array([-0.1, 0.15, 1.4])
    parts = _tapered_branch(start)
    bar_y = 0.15 * occluder_z / 1.4  # across the base, as the camera sees it
    parts[OCCLUDER] = [Cylinder(np.array([-1.0, bar_y, occluder_z]), unit([1, 0, 0]), 2.0, 0.05 * occluder_z / 1.4)]
    result, _ = _estimate(parts)
    if hidden:
        assert not result.branches
        assert "hides the branch at its base" in result.dropped[0].reason
        # a gap larger than the occluder's lead turns the check off
        assert len(_estimate(parts, CutPointConfig(base_occluder_gap_m=0.5))[0].branches) == 1
    else:
        [b] = result.branches
        assert np.linalg.norm(b.cut_point_m - (start + OFFSET * DIRECTION)) < 0.015


def test_a_base_on_the_trunk_is_not_an_occlusion():
    # the trunk's front is nearer than the branch's base by up to its radius: still the base
    scene, base, d = branch_with_trunk(direction=(1.0, 0.0, 0.0))
    masks = masks_from_array(scene.labels, trunk_id=100, kind="instance")
    [b] = estimate_cut_points(masks, scene.disparity, GEOMETRY, CutPointConfig()).branches
    assert np.linalg.norm(b.cut_point_m - (base + OFFSET * d)) < 0.01


def test_the_occluder_gap_must_be_positive():
    with pytest.raises(CutPointConfigError, match="base_occluder_gap_m"):
        CutPointConfig(base_occluder_gap_m=0.0)


def test_a_base_on_the_trunk_below_the_image_gives_no_cut_point():
    # the branch leaves the trunk 4 px below the bottom row; its cut point (5 cm up the branch) would be inside
    # the image, placed by the trunk's cylinder carried beyond the frame
    trunk_x, trunk_z, trunk_r = -0.35, 1.5, 0.08
    direction = unit([1.0, -1.2, 0.0])
    base_y = 0.37  # the bottom row is at y = 0.358 m at 1.5 m
    base = np.array([trunk_x + trunk_r, base_y, trunk_z])
    parts = {
        1: [Cylinder(base, direction, 0.45, 0.015)],
        TRUNK_LABEL: [Cylinder(np.array([trunk_x, -1.0, trunk_z]), unit([0, 1, 0]), 2.0, trunk_r)],
    }
    scene = ray_cast(320, 240, GEOMETRY, parts)
    cut_v = GEOMETRY.cy + GEOMETRY.focal_px * (base + OFFSET * direction)[1] / trunk_z
    assert cut_v < 239, "the true cut point itself is in the image"
    masks = masks_from_array(scene.labels, trunk_id=TRUNK_LABEL, kind="instance")
    result = estimate_cut_points(masks, scene.disparity, GEOMETRY, CutPointConfig())
    assert not result.branches
    assert "meets the trunk outside the image" in result.dropped[0].reason
