"""Which true cut points each frame of a flight shows: what a result of that frame could be scored against.

A flight's truth (`branchrange.offline.flight`) always has the poses and the world cut points;
`visible_cut_ids` per pose is optional (`branchrange synth-flight` writes it from its masks, other
flights may not have it). So the visible set is derived from the geometry when any pose lacks it:
a cut point is visible in a frame when, in that frame's rectified left camera,
- it lies in front (z > 0) and its projection falls inside the image (rectified focal length and
  principal point of the recording's calibration, `camera.rectify.Rectifier`), and
- its distance from the camera is within [`min_distance_m`, `max_distance_m`] — the depth band
  the daemon reports to the autopilot (`mavlink.min_distance_m`, `mavlink.max_distance_m`).
The derived rule cannot see occlusion (a cut point behind another branch counts as visible); the
mask-based `visible_cut_ids`, when every pose has them, are used instead, with the same depth band.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from branchrange.offline.flight import FlightTruth

#: How `visible_in_frames` decided, for reports.
FROM_FLIGHT_JSON = "flight.json visible_cut_ids, within the depth band"
DERIVED = "derived from the poses: in front, inside the image, within the depth band (occlusion not seen)"


@dataclass(frozen=True)
class CameraView:
    """The rectified left camera a flight was recorded with (px) and the depth band (m) the daemon reports."""

    focal_px: float
    cx: float
    cy: float
    width: int
    height: int
    min_distance_m: float
    max_distance_m: float

    @classmethod
    def of(cls, calibration: Any, min_distance_m: float, max_distance_m: float) -> CameraView:
        """The view of a recording's `StereoCalibration` (rectified as the pipeline rectifies it)."""
        from camera.rectify import Rectifier

        rectifier = Rectifier(calibration)
        cx, cy = rectifier.principal_point
        width, height = rectifier.size
        return cls(rectifier.focal_px, cx, cy, width, height, min_distance_m, max_distance_m)

    def in_band(self, point: np.ndarray) -> bool:
        """Whether a camera-frame point `(3,)` m lies within the reported depth band (distance from the camera)."""
        return bool(self.min_distance_m <= float(np.linalg.norm(point)) <= self.max_distance_m)

    def sees(self, point: np.ndarray) -> bool:
        """Whether a camera-frame point `(3,)` m is in front, projects inside the image and is in the band."""
        x, y, z = (float(v) for v in point)
        if z <= 0:
            return False
        u, v = self.focal_px * x / z + self.cx, self.focal_px * y / z + self.cy
        return 0 <= u < self.width and 0 <= v < self.height and self.in_band(point)


def visible_in_frames(truth: FlightTruth, view: CameraView) -> tuple[list[set[int]], str]:
    """Per pose position, the ids of the cut points that frame shows, and which rule decided (module docstring)."""
    recorded = all(pose.visible_cut_ids is not None for pose in truth.poses)
    visible = []
    for position, pose in enumerate(truth.poses):
        in_camera = truth.cut_points_in_camera(position)
        if recorded:
            visible.append({i for i in pose.visible_cut_ids or () if view.in_band(in_camera[i])})
        else:
            visible.append({i for i, point in in_camera.items() if view.sees(point)})
    return visible, FROM_FLIGHT_JSON if recorded else DERIVED
