"""Stable branch ids across frames: 3D association of cut points with gating.

A flight controller (OBSTACLE_DISTANCE_3D obstacle_id) and a replay log must see one branch as one
id while the drone moves. Each frame's cut points are matched to the live tracks by 3D distance
between cut points (gated: farther than `gate_m` never matches; an axis turned by more than
`max_axis_angle_deg` never matches), globally greedy — the closest pair first, which is optimal
whenever the gate separates the candidates, the normal case for branches centimetres to decimetres
apart. Unmatched cut points start new tracks with fresh ids; a track unseen for more than
`max_missed` frames is forgotten and its id is never reused.

A new id on a still camera is not an association fault but a cut point that moved: the replay test's
tree (12 track ids for 10 branches over 4 frames) has one branch, half hidden, whose sgbm estimate
has confidence 0.1–0.2 and jumps 1.8 m in depth and then 0.12 m between frames — beyond any gate
that still separates neighbouring branches. Low-confidence cut points therefore may change id;
the target (confident by policy) keeps its id.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from branchrange.core.cutpoints import BranchEstimate
from branchrange.core.settings_check import Limit, Settings


class TrackerConfigError(ValueError):
    """A tracker setting out of its range; the message names the key."""


@dataclass(frozen=True)
class TrackerConfig(Settings):
    """`[branch_tracking]`, the per-frame branch ids: `gate_m`: largest cut-point displacement
    between frames (m); `max_missed`: frames a track survives unseen; `max_axis_angle_deg`:
    largest change of axis direction that still matches. (`[tracking]` is the world-frame
    target tracks of `branchrange.onboard.mavlink.world_tracks`; `cutpoints.tracking` turns this off.)"""

    section = "branch_tracking"
    error = TrackerConfigError
    limits = {
        "gate_m": Limit(exclusive_minimum=0, expected="> 0 m"),
        "max_missed": Limit(minimum=0, expected="≥ 0 frames"),
        "max_axis_angle_deg": Limit(exclusive_minimum=0, maximum=180, expected="an angle in (0, 180] degrees"),
    }

    gate_m: float = 0.10
    max_missed: int = 5
    max_axis_angle_deg: float = 35.0


@dataclass
class _Track:
    """A live track: its id, last cut point (3,) m, last axis (3,) unit, frames since last seen."""

    track_id: int
    position: np.ndarray
    axis: np.ndarray
    missed: int = 0


class BranchTracker:
    """Assigns `BranchEstimate.id` so that a branch keeps its id from frame to frame."""

    def __init__(self, config: TrackerConfig = TrackerConfig()) -> None:
        self.config = config
        self._tracks: list[_Track] = []
        self._next_id = 0

    @property
    def active_ids(self) -> list[int]:
        """Ids of the tracks alive now."""
        return [t.track_id for t in self._tracks]

    def reset(self) -> None:
        """Forget every track (e.g. after the camera was lost); ids keep counting up."""
        self._tracks.clear()

    def _candidate_pairs(self, branches: list[BranchEstimate]) -> list[tuple[float, int, int]]:
        """(distance, track index, branch index) of every pair inside the gates, nearest first."""
        cos_limit = math.cos(math.radians(self.config.max_axis_angle_deg))
        pairs = []
        for ti, track in enumerate(self._tracks):
            for bi, branch in enumerate(branches):
                distance = float(np.linalg.norm(branch.cut_point_m - track.position))
                if distance > self.config.gate_m:
                    continue
                if float(branch.axis @ track.axis) < cos_limit:
                    continue
                pairs.append((distance, ti, bi))
        return sorted(pairs)

    def update(self, branches: list[BranchEstimate]) -> list[BranchEstimate]:
        """Set each branch's `id` to its track id (new ids for new branches); returns `branches`."""
        taken_tracks: set[int] = set()
        taken_branches: set[int] = set()
        for _, ti, bi in self._candidate_pairs(branches):
            if ti in taken_tracks or bi in taken_branches:
                continue
            taken_tracks.add(ti)
            taken_branches.add(bi)
            track, branch = self._tracks[ti], branches[bi]
            track.position, track.axis, track.missed = branch.cut_point_m.copy(), branch.axis.copy(), 0
            branch.id = track.track_id
        for ti, track in enumerate(self._tracks):
            if ti not in taken_tracks:
                track.missed += 1
        self._tracks = [t for t in self._tracks if t.missed <= self.config.max_missed]
        for bi, branch in enumerate(branches):
            if bi not in taken_branches:
                branch.id = self._next_id
                self._tracks.append(_Track(self._next_id, branch.cut_point_m.copy(), branch.axis.copy()))
                self._next_id += 1
        return branches
