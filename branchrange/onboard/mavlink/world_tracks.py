"""Cut points fused across frames in local NED: one Kalman filter per branch, with an honest covariance,
and a target chosen on evidence, with hysteresis.

**Fusion.** A branch does not move in the world while the drone flies past it, so each track's state
is a static point (3,) in local NED. A frame's cut point, measured in the camera frame and carried to
NED through the mount and the vehicle pose at its capture time, is a measurement z with covariance R:
`lateral σ = lateral_sigma_px · r / f` across the line of sight, `depth σ = disparity_sigma_px · r² /
(f·B)` along it (stereo depth error ∝ range²; f, B the result's camera), both × s^`scale_exponent` for a
branch the region budget matched s times smaller, rotated into NED.

**Honest covariance.** Views of a branch from (nearly) the same viewpoint are not independent: they
share the stereo bias of that viewpoint (the same disparity error on the same pixels), so 20 frames
of a hover must not count as 20 measurements. The error is split into a shared part, `bias_share`·R,
and an independent part, (1 − `bias_share`)·R. The Kalman filter fuses the independent parts (P, with
`process_noise_m2_per_s`·Δt·I between frames for sway and a drifting local position); the shared
part averages down only over *distinct* viewpoints — a new one when the line of sight turned by more
than `same_view_deg` or the range changed by more than `same_view_range_ratio` — so the reported
covariance is P + `bias_share`·R_near / views, R_near the covariance of the nearest observation. One
view: exactly R; n distinct views: R/n; n views from one spot: never below `bias_share`·R.

**Association.** Each cut point joins the nearest live track within `gate_m` (each track takes at most
one per frame, the closest pairs first); an unmatched one starts a track with a fresh id — unless it lies
within `consistency_m` of a track that took a cut point this frame: that is one branch the segmenter split in
two, and a second track for it would only let the target flip between the halves. A track
unseen for `stale_after_s` is not reported (nor sent as an obstacle) but kept, so a branch hidden for
a moment comes back with its id and history; after `forget_after_s` it is dropped.

**Target.** A track may be the target only when (the `TargetRule`)
- its newest observation was captured within `max_age_s` (`mavlink.max_result_age_s`) — one freshness
  rule for every target the relay sends, with or without vehicle state;
- it has `target_min_observations` consistent observations in a row (each within `consistency_m` of
  the track before it was fused; an inconsistent one restarts the count), so a 1–3-frame artefact is
  never the target;
- its fused 1-σ radius is ≤ `target_max_sigma_m`: a track seen a few times from afar, where one view's
  depth σ is centimetres, is not certain enough to fly to (this also ends a target's claim);
- its recency-weighted confidence (`confidence_half_life_s`: an observation's weight halves every
  half-life) is ≥ the rule's `min_confidence` (`cutpoints.target_min_confidence`), so a branch first
  seen uncertain from afar becomes eligible as soon as its recent views are good;
- its newest observation's frame did not refuse it in its light (`Branch.light_refuses_target`: the
  segmenter's calibration in dark or noisy light asks more confidence, or allows no target at all).
Among eligible tracks the cut-point policy ranks (`cutpoints.target_score`, the per-frame rule); the
current target is kept while it holds — still tracked (`stale_after_s`) and confident; one inconsistent
cut point or a frame that missed it does not unseat it — unless another ranks better by
`target_switch_margin` (a share of its score), so the target does not flip between similar branches. While
it holds but its newest cut point is older than `max_age_s`, nothing is sent as the target. The choice is
made at each frame's capture and checked again at each send: a target that no longer holds is replaced by
the best eligible track at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from branchrange.config.sections import TrackingConfig
from branchrange.core.cutpoints import DEFAULT_TARGET_POLICY, target_score
from branchrange.core.frame_result import WorldTrack


@dataclass(frozen=True)
class TargetRule:
    """Which fused track may be the target: cut-point `policy`, `min_confidence` (recency-weighted) and
    `max_age_s`, the oldest capture (s) a target may come from (`mavlink.max_result_age_s`)."""

    policy: str = DEFAULT_TARGET_POLICY
    min_confidence: float = 0.7
    max_age_s: float = 0.5


@dataclass(frozen=True)
class Measurement:
    """One frame's cut point in local NED: `position_m` (3,), `covariance_m2` (3×3, m²), pipeline branch
    id, confidence, `camera_m` (3,) the camera's optical centre in NED at capture, the cut point's
    `diameter_m` (for the `thickest` policy), and whether the frame's light allows it as a target
    (`Branch.light_refuses_target`: the segmenter's calibration in that light asks more confidence)."""

    branch_id: int
    position_m: np.ndarray
    covariance_m2: np.ndarray
    confidence: float
    camera_m: np.ndarray
    diameter_m: float = 0.0
    light_allows_target: bool = True

    @property
    def range_m(self) -> float:
        """Camera → cut point distance (m)."""
        return float(np.linalg.norm(self.position_m - self.camera_m))


def measurement_covariance(
    point_cam_m: np.ndarray,
    cam_to_ned: np.ndarray,
    cfg: TrackingConfig,
    focal_px: float,
    baseline_m: float,
    disparity_scale: int = 1,
) -> np.ndarray:
    """NED covariance (3×3, m²) of a camera-frame cut point (3,) m measured by a camera of `focal_px` (px, full
    resolution) and `baseline_m` (m), its branch matched `disparity_scale` times smaller (the region budget);
    `cam_to_ned` rotates camera → NED."""
    r = float(np.linalg.norm(point_cam_m))
    u = np.asarray(point_cam_m, dtype=np.float64) / max(r, 1e-6)
    along = np.outer(u, u)
    lateral, depth = cfg.sigmas_m(r, focal_px, baseline_m, disparity_scale)
    cov_cam = lateral**2 * (np.eye(3) - along) + depth**2 * along
    rotated: np.ndarray = cam_to_ned @ cov_cam @ cam_to_ned.T
    return rotated


def one_view_sigma_m(
    point_cam_m: np.ndarray, cfg: TrackingConfig, focal_px: float, baseline_m: float, disparity_scale: int = 1
) -> float:
    """The 1-σ radius (m) of one cut point (3,) m in the camera frame, unfused: the larger of its lateral and
    line-of-sight σ (`TrackingConfig.sigmas_m`) — what a target without vehicle state is known to."""
    return max(cfg.sigmas_m(float(np.linalg.norm(point_cam_m)), focal_px, baseline_m, disparity_scale))


@dataclass
class View:
    """A distinct viewpoint of a track: unit line of sight (3,) from the branch to the camera, range (m)."""

    line_of_sight: np.ndarray
    range_m: float


@dataclass
class Track:
    """A fused branch: state `position_m` (3,) NED, filter covariance `filter_covariance_m2` (3×3, the
    independent part), its evidence, and what the target choice reads."""

    track_id: int
    position_m: np.ndarray
    filter_covariance_m2: np.ndarray
    near_covariance_m2: np.ndarray
    last_seen: float
    branch_id: int
    confidence: float  # recency-weighted: an observation's weight halves every `confidence_half_life_s`
    distance_m: float
    diameter_m: float
    views: list[View]
    observations: int = 1
    consistent_observations: int = 1
    light_allows_target: bool = True  # as its newest observation's frame said
    bias_share: float = TrackingConfig.bias_share
    updated_at: float = field(default=0.0)

    @classmethod
    def start(cls, track_id: int, z: Measurement, t: float, cfg: TrackingConfig) -> Track:
        """A new track from its first measurement `z`, captured at `t` (s)."""
        return cls(
            track_id,
            z.position_m.copy(),
            (1.0 - cfg.bias_share) * z.covariance_m2,
            z.covariance_m2.copy(),
            t,
            z.branch_id,
            z.confidence,
            z.range_m,
            z.diameter_m,
            [_view_of(z)],
            light_allows_target=z.light_allows_target,
            bias_share=cfg.bias_share,
            updated_at=t,
        )

    @property
    def covariance_m2(self) -> np.ndarray:
        """Reported covariance (3×3, m²): the filter's plus the shared bias, averaged over distinct views."""
        return self.filter_covariance_m2 + self.bias_share * self.near_covariance_m2 / len(self.views)

    @property
    def sigma_m(self) -> float:
        """1-σ radius (m): the square root of the reported covariance's largest eigenvalue."""
        return math.sqrt(max(0.0, float(np.linalg.eigvalsh(self.covariance_m2)[-1])))

    def age(self, now: float) -> float:
        """Seconds since the newest observation was captured."""
        return now - self.last_seen

    def predict(self, t: float, process_noise_m2_per_s: float) -> None:
        """Grow the filter covariance for the time since the last update."""
        if t > self.updated_at:
            self.filter_covariance_m2 = self.filter_covariance_m2 + process_noise_m2_per_s * (
                t - self.updated_at
            ) * np.eye(3)
            self.updated_at = t

    def update(self, z: Measurement, t: float, cfg: TrackingConfig) -> None:
        """Fuse one measurement: Kalman update of a static point with its independent part, the
        consistency count, the recency-weighted confidence and the distinct views."""
        consistent = float(np.linalg.norm(z.position_m - self.position_m)) <= cfg.consistency_m
        noise = (1.0 - cfg.bias_share) * z.covariance_m2
        gain = self.filter_covariance_m2 @ np.linalg.inv(self.filter_covariance_m2 + noise)
        self.position_m = self.position_m + gain @ (z.position_m - self.position_m)
        covariance = (np.eye(3) - gain) @ self.filter_covariance_m2
        self.filter_covariance_m2 = (covariance + covariance.T) / 2.0
        if np.trace(z.covariance_m2) < np.trace(self.near_covariance_m2):
            self.near_covariance_m2 = z.covariance_m2.copy()
        view = _view_of(z)
        if not any(_same_view(view, seen, cfg) for seen in self.views):
            self.views.append(view)
        weight_kept = 0.5 ** (max(t - self.last_seen, 0.0) / cfg.confidence_half_life_s)
        self.confidence = weight_kept * self.confidence + (1.0 - weight_kept) * z.confidence
        self.observations += 1
        self.consistent_observations = self.consistent_observations + 1 if consistent else 1
        self.last_seen = max(self.last_seen, t)
        self.branch_id = z.branch_id
        self.distance_m, self.diameter_m = z.range_m, z.diameter_m
        self.light_allows_target = z.light_allows_target

    def score(self, policy: str) -> float:
        """The cut-point policy's rank of this track (lower is better)."""
        return target_score(policy, self.distance_m, max(self.confidence, 1e-6), self.diameter_m)

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
            covariance_m2=rows,  # type: ignore[arg-type]
            age_s=round(max(self.age(now), 0.0), 3),
            observations=self.observations,
            consistent_observations=self.consistent_observations,
            views=len(self.views),
            confidence=round(self.confidence, 3),
        )


def _view_of(z: Measurement) -> View:
    """The viewpoint of a measurement: unit line of sight from the cut point to the camera, and the range."""
    distance = z.range_m
    return View((z.camera_m - z.position_m) / max(distance, 1e-9), distance)


def _same_view(a: View, b: View, cfg: TrackingConfig) -> bool:
    """Whether two viewpoints are within `same_view_deg` and their ranges within `same_view_range_ratio`."""
    cos_angle = float(np.clip(a.line_of_sight @ b.line_of_sight, -1.0, 1.0))
    return math.degrees(math.acos(cos_angle)) <= cfg.same_view_deg and abs(
        math.log(max(a.range_m, 1e-9) / max(b.range_m, 1e-9))
    ) <= math.log1p(cfg.same_view_range_ratio)


class WorldTracks:
    """The set of fused branch tracks and which one is the target (see the module docstring)."""

    def __init__(self, cfg: TrackingConfig = TrackingConfig(), rule: TargetRule = TargetRule()):
        self.cfg = cfg
        self.rule = rule
        self.tracks: list[Track] = []
        self.target_id: int | None = None
        self.target_switches = 0
        self._next_id = 0

    def update(self, measurements: list[Measurement], t: float) -> dict[int, int]:
        """Fuse one frame's measurements taken at time `t` (s), then choose the target; returns branch
        id → track id."""
        self._forget(t)
        for track in self.tracks:
            track.predict(t, self.cfg.process_noise_m2_per_s)
        pairs = sorted(
            (_distance(z.position_m, tr.position_m), ti, zi)
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
            self.tracks[ti].update(measurements[zi], t, self.cfg)
            used_tracks.add(ti)
            matched[zi] = self.tracks[ti].track_id
        taken = [self.tracks[ti] for ti in used_tracks]
        for zi, z in enumerate(measurements):
            if zi not in matched:
                twin = next(
                    (tr for tr in taken if _distance(z.position_m, tr.position_m) <= self.cfg.consistency_m), None
                )
                if twin is not None:  # the same branch seen twice this frame (a split instance): no second track
                    matched[zi] = twin.track_id
                    continue
                track = Track.start(self._next_id, z, t, self.cfg)
                self._next_id += 1
                self.tracks.append(track)
                matched[zi] = track.track_id
        self._choose_target(t)
        return {measurements[zi].branch_id: tid for zi, tid in matched.items()}

    def holds(self, track: Track, now: float) -> bool:
        """Whether the current target `track` keeps its claim at `now` (s): still tracked (seen within
        `stale_after_s`) and confident enough. Its run of consistent observations is what it took to become
        the target: one inconsistent cut point (a noisy frame) does not hand the target to another branch,
        nor does a frame or two that missed it."""
        return (
            track.age(now) <= self.cfg.stale_after_s
            and track.confidence >= self.rule.min_confidence
            and track.light_allows_target
            and track.sigma_m <= self.cfg.target_max_sigma_m
        )

    def sendable(self, track: Track, now: float) -> bool:
        """Whether a target `track` may go out at `now` (s): its newest cut point captured within `max_age_s`."""
        return 0.0 <= track.age(now) <= self.rule.max_age_s

    def eligible(self, track: Track, now: float) -> bool:
        """Whether `track` may become the target at `now` (s): fresh, confident, consistent and certain enough."""
        return (
            self.sendable(track, now)
            and track.confidence >= self.rule.min_confidence
            and track.light_allows_target
            and track.consistent_observations >= self.cfg.target_min_observations
            and track.sigma_m <= self.cfg.target_max_sigma_m
        )

    def _choose_target(self, now: float) -> None:
        """Keep the current target while it holds, unless an eligible track ranks better by the margin."""
        current = next((tr for tr in self.tracks if tr.track_id == self.target_id and self.holds(tr, now)), None)
        candidates = [tr for tr in self.tracks if self.eligible(tr, now)]
        best = min(candidates, key=lambda tr: tr.score(self.rule.policy), default=None)
        if best is None or current is None:
            chosen = best if current is None else current
        elif best is not current and _better_by(
            best.score(self.rule.policy), current.score(self.rule.policy), self.cfg
        ):
            chosen = best
        else:
            chosen = current
        new_id = None if chosen is None else chosen.track_id
        if new_id is not None and self.target_id is not None and new_id != self.target_id:
            self.target_switches += 1
        self.target_id = new_id

    def _forget(self, now: float) -> None:
        """Drop tracks unseen for `forget_after_s`."""
        self.tracks = [tr for tr in self.tracks if tr.age(now) <= self.cfg.forget_after_s]
        if self.target_id is not None and all(tr.track_id != self.target_id for tr in self.tracks):
            self.target_id = None

    def fresh(self, now: float) -> list[Track]:
        """Tracks seen within `stale_after_s` of `now` (sent as obstacles, reported in results)."""
        return [tr for tr in self.tracks if tr.age(now) <= self.cfg.stale_after_s]

    def target(self, now: float) -> Track | None:
        """The target track to send at `now` (s), None when there is none to send. The choice made at the
        last frame's capture is checked again at `now`: a target that no longer holds (stale, or no longer
        confident) is replaced by the best eligible track at once; one that holds but whose newest cut
        point is older than `max_age_s` keeps its claim and sends nothing meanwhile (a frame or two that
        missed it must not swing the approach to another branch)."""
        current = next((tr for tr in self.tracks if tr.track_id == self.target_id), None)
        if current is None or not self.holds(current, now):
            self._choose_target(now)
            current = next((tr for tr in self.tracks if tr.track_id == self.target_id), None)
        return current if current is not None and self.sendable(current, now) else None

    def reset(self) -> None:
        """Forget every track (ids keep counting up)."""
        self.tracks.clear()
        self.target_id = None


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    """Euclidean distance between two points (3,), metres."""
    return float(np.linalg.norm(a - b))


def _better_by(candidate_score: float, current_score: float, cfg: TrackingConfig) -> bool:
    """Whether a score (lower is better) beats the current one by `target_switch_margin` of its size."""
    return candidate_score < current_score - cfg.target_switch_margin * abs(current_score)
