"""Coarse-to-fine planning (`branchrange.core.roi`): boxes, disparity windows and which instances get a fine pass."""

from __future__ import annotations

import numpy as np
import pytest

from branchrange.core.geometry import StereoGeometry
from branchrange.core.masks import BranchMasks
from branchrange.core.roi import (
    DISPARITY_STEP,
    RoiConfig,
    coarse_scale,
    disparity_window,
    plan_regions,
    refine_labels,
    scaled_geometry,
)
from branchrange.core.settings_check import ConfigError


def test_disparity_window_covers_the_instance_in_whole_steps():
    coarse = np.full(200, 20.0)
    coarse[:100] = 24.0
    d_min, d_range = disparity_window(coarse, scale=2, margin_px=8, max_disp=128)
    assert d_min <= 40 - 8 and d_min + d_range >= 48 + 8 and d_range % DISPARITY_STEP == 0
    assert d_range <= 32  # narrow: the point of the fine pass
    # a few background pixels at the silhouette do not widen it (2nd–98th percentile)
    assert disparity_window(np.concatenate([coarse, [1.0]]), 2, 8, 128) == (d_min, d_range)
    # no evidence: the whole range; near the top of the range: clipped inside it
    assert disparity_window(np.array([30.0]), 2, 8, 128) == (0, 128)
    low, span = disparity_window(np.full(50, 62.0), 2, 8, 128)
    assert low + span <= 128 and low <= 124 - 8


def test_plan_gives_each_branch_a_region_and_keeps_the_nearest():
    labels = np.zeros((40, 80), np.int32)
    coarse_disp = np.zeros((20, 40), np.float32)
    labels[0:40, 0:8] = 65535  # the trunk, far
    coarse_disp[:, 0:4] = 5.0
    for k, x in enumerate(range(10, 80, 10), start=1):
        labels[10:30, x : x + 4] = k
        coarse_disp[5:15, x // 2 : x // 2 + 2] = 10.0 + k  # branch k: nearer with k
    regions = plan_regions(
        BranchMasks(labels, 65535), labels[::2, ::2], coarse_disp, 2, RoiConfig(max_regions=3, box_margin_px=2), 128
    )
    assert [r.instance_id for r in regions] == [5, 6, 7]  # the trunk keeps its coarse disparity
    assert regions[-1].box == (68, 8, 76, 32)  # branch 7 at x 70..73, y 10..29, grown by 2 px


def test_by_default_every_instance_a_learned_segmenter_gives_gets_a_fine_pass():
    # the learned segmenter gives up to ~40 instances on a frame (fragments and doubtful pieces too): an instance
    # without a region is dropped, so the default bound must not be what decides which branches are kept
    labels = np.zeros((80, 400), np.int32)
    coarse_disp = np.zeros((40, 200), np.float32)
    for k, x in enumerate(range(0, 400, 10), start=1):
        labels[10:70, x : x + 4] = k
        coarse_disp[5:35, x // 2 : x // 2 + 2] = 10.0 + 0.1 * k
    regions = plan_regions(BranchMasks(labels, None), labels[::2, ::2], coarse_disp, 2, RoiConfig(), 128)
    assert len(regions) == 40


def test_refined_labels_follow_the_fine_disparity_inside_the_window():
    coarse = np.zeros((10, 20), np.int32)
    coarse[3:6, 5:8] = 1
    fine = np.zeros((20, 40), np.float32)
    fine[5:13, 9:17] = 40.0  # the branch at full resolution, slightly wider than its coarse cells
    fine[0:20, 0:9] = 10.0  # background, outside the window
    from branchrange.core.roi import Region

    coarse[0:2, 0:2] = 9  # the trunk: kept as up-sampled, it has no fine pass
    upsampled = np.kron(coarse, np.ones((2, 2), np.int32))
    labels = refine_labels(upsampled, 2, fine, [Region(1, (0, 0, 40, 20), 32, 16)], trunk_id=9)
    assert np.array_equal(labels == 1, fine == 40.0)
    assert np.array_equal(labels == 9, upsampled == 9)


def test_the_trunk_takes_the_coarse_disparity_on_every_scale_th_pixel():
    from types import SimpleNamespace

    from branchrange.core.roi import trunk_from_coarse

    labels = np.zeros((8, 12), np.int32)
    labels[:, 2:6] = 65535
    coarse = SimpleNamespace(disparity=np.full((4, 6), 7.0, np.float32), confidence=np.full((4, 6), 0.5, np.float32))
    disparity, confidence = np.zeros((8, 12), np.float32), np.zeros((8, 12), np.float32)
    trunk_from_coarse(disparity, confidence, labels, 65535, coarse, 2)
    expected = np.zeros((8, 12), bool)
    expected[1::2, 3:6:2] = True  # the trunk's pixels on the stride-2 grid (offset 1)
    assert np.array_equal(disparity > 0, expected) and np.all(disparity[expected] == 14.0)
    assert np.all(confidence[expected] == 0.5)


def test_coarse_scale_and_geometry():
    assert coarse_scale(1280, 640) == 2 and coarse_scale(1920, 640) == 3 and coarse_scale(800, 640) == 1
    g = scaled_geometry(StereoGeometry(640.0, 0.063, 639.5, 359.5), 2)
    assert (g.focal_px, g.baseline_m, g.cx, g.cy) == (320.0, 0.063, 319.5, 179.5)


def test_roi_settings_are_checked():
    with pytest.raises(ConfigError, match="roi.max_regions"):
        RoiConfig(max_regions=0)
