"""Stable branch ids across frames: gating, global greedy association, track ageing."""

from __future__ import annotations

import re

import numpy as np
import pytest

from branchrange.core.cutpoints import BranchEstimate
from branchrange.core.tracking import BranchTracker, TrackerConfig, TrackerConfigError


def branch(x, y=0.0, z=1.5, axis=(1.0, 0.0, 0.0), mask_id=1) -> BranchEstimate:
    point = np.array([x, y, z])
    a = np.asarray(axis, dtype=float)
    return BranchEstimate(
        mask_id, point, point, a / np.linalg.norm(a), float(np.linalg.norm(point)), (0.0, 0.0), 0.02, 0.9, 1.0, 0.0, 100
    )


def ids(branches):
    return [b.id for b in branches]


def test_branches_keep_their_ids_while_the_camera_moves():
    tracker = BranchTracker()
    first = tracker.update([branch(0.0), branch(0.3), branch(-0.4)])
    assert ids(first) == [0, 1, 2]
    # next frame: every branch moved 3 cm, order shuffled, mask ids renumbered
    moved = tracker.update([branch(-0.37, mask_id=1), branch(0.03, mask_id=2), branch(0.33, mask_id=3)])
    assert ids(moved) == [2, 0, 1]


def test_a_jump_beyond_the_gate_starts_a_new_track():
    tracker = BranchTracker(TrackerConfig(gate_m=0.05))
    tracker.update([branch(0.0)])
    assert ids(tracker.update([branch(0.08)])) == [1]
    assert tracker.active_ids == [0, 1]


def test_closest_pair_wins_when_two_branches_compete_for_one_track():
    tracker = BranchTracker()
    tracker.update([branch(0.0)])
    out = tracker.update([branch(0.06), branch(0.01)])
    assert ids(out) == [1, 0]


def test_a_turned_axis_does_not_match():
    tracker = BranchTracker(TrackerConfig(max_axis_angle_deg=30))
    tracker.update([branch(0.0, axis=(1, 0, 0))])
    assert ids(tracker.update([branch(0.01, axis=(0, 1, 0))])) == [1]


def test_tracks_survive_short_gaps_and_expire_after_max_missed():
    tracker = BranchTracker(TrackerConfig(max_missed=2))
    tracker.update([branch(0.0)])
    tracker.update([])
    tracker.update([])
    assert ids(tracker.update([branch(0.01)])) == [0]  # two missed frames: still alive
    for _ in range(3):
        tracker.update([])
    assert tracker.active_ids == []
    assert ids(tracker.update([branch(0.0)])) == [1]  # ids are never reused


def test_reset_forgets_tracks_but_not_the_id_counter():
    tracker = BranchTracker()
    tracker.update([branch(0.0), branch(0.5)])
    tracker.reset()
    assert ids(tracker.update([branch(0.0)])) == [2]


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"gate_m": 0}, "branch_tracking.gate_m = 0: expected > 0 m"),
        ({"max_missed": -1}, "branch_tracking.max_missed = -1: expected ≥ 0 frames"),
        ({"max_axis_angle_deg": 0}, "branch_tracking.max_axis_angle_deg = 0: expected an angle"),
    ],
)
def test_config_errors_name_the_key_value_and_expectation(kwargs, message):
    with pytest.raises(TrackerConfigError, match=re.escape(message)):
        TrackerConfig(**kwargs)
