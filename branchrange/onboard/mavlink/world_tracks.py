"""Cut points fused across frames in local NED: one Kalman filter per branch, with a covariance.

A branch does not move in the world while the drone flies past it, so each track's state is a
static point (3,) in local NED with covariance P (3×3, m²). A frame's cut point, measured in the
camera frame and carried to NED through the mount and the vehicle pose at its capture time, is a
measurement z with covariance R: `lateral σ = lateral_sigma_at_1m_m · r` across the line of sight,
`depth σ = depth_sigma_at_1m_m · r²` along it (stereo depth error ∝ range²), rotated into NED.
Between frames P grows by `process_noise_m2_per_s · Δt · I` (a branch swaying in the wind, a local
position estimate that drifts). Update: K = P (P + R)⁻¹, x += K (z − x), P = (I − K) P; the error
falls as observations add up (∝ 1/√n for equal measurements).

Association: each cut point joins the nearest live track within `gate_m` (each track takes at most
one per frame, the closest pairs first); an unmatched one starts a track with a fresh id. A track
unseen for `stale_after_s` is not reported as fresh (not sent, not a target) but is kept, so a
branch hidden for a moment comes back with its id and history; after `forget_after_s` it is dropped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from branchrange.core.config import TrackingConfig
from branchrange.core.frame_result import WorldTrack


@dataclass(frozen=True)
class Measurement:
    """One frame's cut point in local NED: `position_m` (3,), `covariance_m2` (3×3), pipeline branch id."""

    branch_id: int
    position_m: np.ndarray
    covariance_m2: np.ndarray
    confidence: float


def measurement_covariance(point_cam_m: np.ndarray, cam_to_ned: np.ndarray, cfg: TrackingConfig) -> np.ndarray:
    """NED covariance (3×3, m²) of a camera-frame cut point (3,) m; `cam_to_ned` rotates camera → NED."""
    r = float(np.linalg.norm(point_cam_m))
    u = np.asarray(point_cam_m, dtype=np.float64) / max(r, 1e-6)
    along = np.outer(u, u)
    cov_cam = (cfg.lateral_sigma_at_1m_m * r) ** 2 * (np.eye(3) - along) + (
        cfg.depth_sigma_at_1m_m * r * r
    ) ** 2 * along
    return cam_to_ned @ cov_cam @ cam_to_ned.T


@dataclass
class Track:
    """A fused branch: state `position_m` (3,) NED, `covariance_m2` (3×3), when and how often seen."""

    track_id: int
    position_m: np.ndarray
    covariance_m2: np.ndarray
    last_seen: float
    branch_id: int
    observations: int = 1
    confidence_sum: float = 0.0
    updated_at: float = field(default=0.0)

    @property
    def confidence(self) -> float:
        """Mean confidence of the cut points fused into the track."""
        return self.confidence_sum / self.observations

    @property
    def sigma_m(self) -> float:
        """1-σ radius (m): the square root of the covariance's largest eigenvalue."""
        return math.sqrt(max(0.0, float(np.linalg.eigvalsh(self.covariance_m2)[-1])))

    def predict(self, t: float, process_noise_m2_per_s: float) -> None:
        """Grow the covariance for the time since the last update."""
        if t > self.updated_at:
            self.covariance_m2 = self.covariance_m2 + process_noise_m2_per_s * (t - self.updated_at) * np.eye(3)
            self.updated_at = t

    def update(self, z: Measurement, t: float) -> None:
        """Fuse one measurement (Kalman update of a static point)."""
        gain = self.covariance_m2 @ np.linalg.inv(self.covariance_m2 + z.covariance_m2)
        self.position_m = self.position_m + gain @ (z.position_m - self.position_m)
        self.covariance_m2 = (np.eye(3) - gain) @ self.covariance_m2
        self.covariance_m2 = (self.covariance_m2 + self.covariance_m2.T) / 2.0
        self.observations += 1
        self.confidence_sum += z.confidence
        self.last_seen = max(self.last_seen, t)
        self.branch_id = z.branch_id

    def summary(self, now: float) -> WorldTrack:
        """The track as a result reports it at time `now` (s): metres rounded to 0.1 mm, m² to 3
        significant digits, seconds to ms (for /latest and the JSONL log)."""
        x, y, z = (round(float(v), 4) for v in self.position_m)
        rows = tuple(tuple(float(f"{v:.3g}") for v in row) for row in self.covariance_m2)
        return WorldTrack(
            id=self.track_id,
            branch_id=self.branch_id,
            ned_m=(x, y, z),
            sigma_m=round(self.sigma_m, 4),
            covariance_m2=rows,
            age_s=round(now - self.last_seen, 3),  # type: ignore[arg-type]
            observations=self.observations,
            confidence=round(self.confidence, 3),
        )


class WorldTracks:
    """The set of fused branch tracks and which one is the target."""

    def __init__(self, cfg: TrackingConfig = TrackingConfig()):
        self.cfg = cfg
        self.tracks: list[Track] = []
        self.target_id: int | None = None
        self._next_id = 0

    def update(self, measurements: list[Measurement], t: float, target_branch: int | None) -> dict[int, int]:
        """Fuse one frame's measurements taken at time `t` (s); returns branch id → track id.

        `target_branch` (the result's `target_id`) makes its track the target; a frame without a
        target keeps the previous target track, so a briefly hidden target stays the target.
        """
        self._forget(t)
        for track in self.tracks:
            track.predict(t, self.cfg.process_noise_m2_per_s)
        pairs = sorted(
            (float(np.linalg.norm(z.position_m - tr.position_m)), ti, zi)
            for ti, tr in enumerate(self.tracks)
            for zi, z in enumerate(measurements)
        )
        used_tracks: set[int] = set()
        matched: dict[int, int] = {}
        for dist, ti, zi in pairs:
            if dist > self.cfg.gate_m:
                break
            if ti in used_tracks or zi in matched:
                continue
            self.tracks[ti].update(measurements[zi], t)
            used_tracks.add(ti)
            matched[zi] = self.tracks[ti].track_id
        for zi, z in enumerate(measurements):
            if zi not in matched:
                track = Track(
                    self._next_id,
                    z.position_m.copy(),
                    z.covariance_m2.copy(),
                    t,
                    z.branch_id,
                    confidence_sum=z.confidence,
                    updated_at=t,
                )
                self._next_id += 1
                self.tracks.append(track)
                matched[zi] = track.track_id
        by_branch = {measurements[zi].branch_id: tid for zi, tid in matched.items()}
        if target_branch is not None and target_branch in by_branch:
            self.target_id = by_branch[target_branch]
        return by_branch

    def _forget(self, now: float) -> None:
        """Drop tracks unseen for `forget_after_s`."""
        self.tracks = [tr for tr in self.tracks if now - tr.last_seen <= self.cfg.forget_after_s]
        if self.target_id is not None and all(tr.track_id != self.target_id for tr in self.tracks):
            self.target_id = None

    def fresh(self, now: float) -> list[Track]:
        """Tracks seen within `stale_after_s` of `now`."""
        return [tr for tr in self.tracks if now - tr.last_seen <= self.cfg.stale_after_s]

    def target(self, now: float) -> Track | None:
        """The target track while it is fresh, else None."""
        return next((tr for tr in self.fresh(now) if tr.track_id == self.target_id), None)

    def reset(self) -> None:
        """Forget every track (ids keep counting up)."""
        self.tracks.clear()
        self.target_id = None
