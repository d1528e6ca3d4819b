"""Overlay labels: distance and confidence a person can read, the target named as such, and
labels that neither overlap each other nor leave the frame, even for a crowd of close branches."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
from result_factory import branch, frame_result

from branchrange.core.frame_result import FrameResult
from branchrange.core.overlay import Box, draw_overlay, label_parts, layout_labels, place_labels, status_parts


def crowded_result(count: int, width: int, height: int, seed: int = 0) -> FrameResult:
    """`count` branches whose cut points sit within 40 px of each other near the right edge."""
    rng = np.random.default_rng(seed)
    branches = []
    for i in range(count):
        u, v = width - 20 + rng.uniform(-20, 15), height / 2 + rng.uniform(-20, 20)
        z = 1.0 + 0.05 * i
        branches.append(
            replace(
                branch(90 + i, [0.1, 0.0, z], confidence=0.87 - 0.01 * i, pixel=(u, v), axis=(0.0, -1.0, 0.0)),
                distance_m=z,
            )
        )
    return frame_result(branches, target_id=93 if count > 3 else None, width=width, height=height, focal_px=500.0)


def test_label_text_is_distance_and_confidence_and_names_the_target():
    one = replace(branch(1, [0.0, 0.0, 1.234]), confidence=0.871)
    assert label_parts(one, is_target=False) == ["1.23 m", "87 %"]
    assert label_parts(one, is_target=True) == ["TARGET", "1.23 m", "87 %"]
    result = crowded_result(5, 640, 360)
    assert status_parts(result) == ["5 cut points", "target 1.15 m"]
    assert status_parts(crowded_result(2, 640, 360), unlabelled=1) == [
        "2 cut points",
        "no target",
        "1 unlabelled (no room)",
    ]
    assert "#" not in " ".join(status_parts(result))


@pytest.mark.parametrize(("count", "size"), [(12, (640, 360)), (25, (1280, 720))])
def test_many_close_branches_get_labels_inside_the_frame_without_overlap(count, size):
    width, height = size
    result = crowded_result(count, width, height)
    status, labels = layout_labels(result, width, height, scale=max(0.35, width / 1600), clearance=12)
    boxes = [box for _, _, box in labels]
    assert all(box is not None for box in boxes)  # there is room for all of them here
    for box in [status, *boxes]:
        assert box.inside(width, height), box
    for a, b in itertools.combinations([status, *boxes], 2):
        assert not a.intersects(b), (a, b)
    assert labels[0][0].id == 93 and labels[0][1][0] == "TARGET"  # the target is placed first
    image = draw_overlay(np.full((height, width, 3), 90, np.uint8), result)
    assert image.shape == (height, width, 3)


def test_a_label_that_finds_no_room_is_left_out_rather_than_overlapping():
    boxes = place_labels([(50, 20)] * 4, [(60, 18)] * 4, (100, 40))
    placed = [b for b in boxes if b is not None]
    assert 1 <= len(placed) < 4
    for a, b in itertools.combinations(placed, 2):
        assert not a.intersects(b)
    assert all(b.inside(100, 40) for b in placed)


def test_boxes_reserved_for_the_status_line_are_kept_free():
    reserved = Box(0, 0, 100, 30)
    [box] = place_labels([(10, 10)], [(50, 16)], (200, 100), reserved=[reserved])
    assert box is not None and not box.intersects(reserved) and box.inside(200, 100)
