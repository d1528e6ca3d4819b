"""Which fused track is the target: evidence before trust, hysteresis, recency-weighted readiness, freshness."""

from __future__ import annotations

import numpy as np

from branchrange.config.sections import TrackingConfig
from branchrange.onboard.mavlink.world_tracks import Measurement, TargetRule, WorldTracks

CAMERA = np.zeros(3)
COVARIANCE = np.eye(3) * 1e-4
FPS = 15.0


def seen(branch_id: int, position, confidence: float = 0.9) -> Measurement:
    """A cut point at `position` (NED m) seen from the origin."""
    return Measurement(branch_id, np.asarray(position, dtype=float), COVARIANCE, confidence, CAMERA)


def test_a_track_is_the_target_only_after_enough_consistent_observations():
    tracks = WorldTracks(TrackingConfig(target_min_observations=3), TargetRule(min_confidence=0.5))
    for k in range(2):
        tracks.update([seen(0, [1.5, 0.0, 0.0])], k / FPS)
        assert tracks.target(k / FPS) is None  # a 1–2-observation track is not trusted yet
    tracks.update([seen(0, [1.5, 0.0, 0.0])], 2 / FPS)
    assert tracks.target(2 / FPS) is not None


def test_an_inconsistent_observation_restarts_the_count():
    cfg = TrackingConfig(target_min_observations=3, consistency_m=0.05, gate_m=0.15)
    tracks = WorldTracks(cfg, TargetRule(min_confidence=0.5))
    positions = [[1.5, 0, 0], [1.5, 0, 0], [1.5, 0.1, 0], [1.5, 0.1, 0]]  # a 10 cm jump, within the gate
    for k, p in enumerate(positions):
        tracks.update([seen(0, p)], k / FPS)
    (track,) = tracks.tracks
    assert track.observations == 4 and track.consistent_observations < 3
    assert tracks.target(3 / FPS) is None


def test_the_target_holds_against_a_similar_branch_and_yields_to_a_clearly_better_one():
    tracks = WorldTracks(
        TrackingConfig(target_min_observations=1, target_switch_margin=0.2), TargetRule(min_confidence=0.5)
    )
    near, similar = [1.50, 0.0, 0.0], [1.0, 1.15, 0.0]  # 1.50 m and 1.52 m away
    ids = tracks.update([seen(0, near), seen(1, similar)], 0.0)
    first = tracks.target_id
    assert first == ids[0]
    # the per-frame ranking flips (the other one looks nearer this frame): the target stays
    for k in range(1, 10):
        nearer = [1.0, 1.05, 0.0] if k % 2 else similar  # 1.45 m: 3 % better, under the 20 % margin
        tracks.update([seen(0, near), seen(1, nearer)], k / FPS)
        assert tracks.target_id == first
    assert tracks.target_switches == 0
    # a branch 40 % nearer takes over
    tracks.update([seen(0, near), seen(1, similar), seen(2, [0.9, 0.0, 0.0])], 10 / FPS)
    assert tracks.target(10 / FPS).branch_id == 2 and tracks.target_switches == 1


def test_readiness_follows_recent_confidence_not_the_lifetime_mean():
    cfg = TrackingConfig(target_min_observations=3, confidence_half_life_s=0.4)
    tracks = WorldTracks(cfg, TargetRule(min_confidence=0.7))
    t = 0.0
    for _ in range(40):  # first seen unsure from afar
        tracks.update([seen(0, [3.0, 0, 0], confidence=0.3)], t)
        t += 1 / FPS
    assert tracks.target(t) is None
    rose_at = t
    while True:
        tracks.update([seen(0, [3.0, 0, 0], confidence=0.85)], t)
        if tracks.target(t) is not None:
            break
        t += 1 / FPS
        assert t - rose_at < 1.0, "ready within 1 s of its views turning confident"
    (track,) = tracks.tracks
    lifetime_mean = (40 * 0.3 + (track.observations - 40) * 0.85) / track.observations
    assert lifetime_mean < 0.7 <= track.confidence


def test_a_target_from_a_capture_older_than_the_age_limit_is_not_the_target():
    tracks = WorldTracks(TrackingConfig(target_min_observations=1), TargetRule(min_confidence=0.5, max_age_s=0.5))
    tracks.update([seen(0, [1.5, 0, 0])], 10.0)
    assert tracks.target(10.49) is not None
    assert tracks.target(10.51) is None
    assert tracks.fresh(10.51)  # still an obstacle


def test_a_branch_its_frames_light_refuses_is_not_the_target():
    tracks = WorldTracks(TrackingConfig(target_min_observations=1), TargetRule(min_confidence=0.5))
    tracks.update([seen(0, [1.5, 0, 0])], 0.0)
    assert tracks.target(0.0) is not None
    dark = Measurement(0, np.array([1.5, 0, 0]), COVARIANCE, 0.9, CAMERA, light_allows_target=False)
    tracks.update([dark], 0.1)  # the light now asks more than its 0.9
    assert tracks.target(0.1) is None
    tracks.update([seen(0, [1.5, 0, 0])], 0.2)  # back in normal light
    assert tracks.target(0.2) is not None


def test_one_inconsistent_cut_point_does_not_hand_the_target_to_a_similar_branch():
    cfg = TrackingConfig(target_min_observations=3, consistency_m=0.05, target_switch_margin=0.2)
    tracks = WorldTracks(cfg, TargetRule(min_confidence=0.5))
    near, similar = [1.50, 0.0, 0.0], [1.0, 1.15, 0.0]  # 1.50 m and 1.52 m away
    for k in range(4):
        tracks.update([seen(0, near), seen(1, similar)], k / FPS)
    first = tracks.target_id
    tracks.update([seen(0, [1.5, 0.08, 0.0]), seen(1, similar)], 4 / FPS)  # a noisy frame: 8 cm off, in the gate
    assert tracks.tracks[0].consistent_observations == 1 and tracks.target_id == first
    assert tracks.target_switches == 0


def test_a_target_missed_for_a_moment_keeps_its_claim_and_gives_way_once_stale():
    cfg = TrackingConfig(target_min_observations=1, stale_after_s=1.5)
    tracks = WorldTracks(cfg, TargetRule(min_confidence=0.5, max_age_s=0.5))
    tracks.update([seen(0, [1.5, 0, 0])], 0.0)  # the target
    sent = {}
    for k in range(1, 18):  # then only a farther branch is seen, every 0.1 s; a send after each frame
        t = round(0.1 * k, 1)
        tracks.update([seen(1, [2.5, 0, 0])], t)
        target = tracks.target(t)
        sent[t] = None if target is None else target.branch_id
    assert sent[0.4] == 0
    assert sent[0.6] is None and sent[1.5] is None  # 0 still holds but is too old to send: nothing goes out
    assert sent[1.6] == 1  # 0 went stale: the eligible one takes over at once
    assert tracks.target_switches == 1
    assert tracks.target(2.3) is None  # both too old


def test_a_clearly_better_branch_takes_over_even_while_the_target_holds():
    cfg = TrackingConfig(target_min_observations=1, target_switch_margin=0.2)
    tracks = WorldTracks(cfg, TargetRule(min_confidence=0.5, max_age_s=0.5))
    tracks.update([seen(0, [2.0, 0, 0])], 0.0)
    tracks.update([seen(1, [1.0, 0, 0])], 0.6)  # half as far: better by more than the margin
    assert tracks.target(0.6).branch_id == 1


def test_a_branch_split_in_two_this_frame_gets_one_track_not_two():
    tracks = WorldTracks(TrackingConfig(consistency_m=0.05), TargetRule(min_confidence=0.5))
    tracks.update([seen(0, [1.5, 0.0, 0.0])], 0.0)
    ids = tracks.update([seen(3, [1.5, 0.0, 0.0]), seen(4, [1.5, 0.03, 0.0])], 0.1)  # two instances, 3 cm apart
    assert len(tracks.tracks) == 1 and ids == {3: 0, 4: 0}
    tracks.update([seen(3, [1.5, 0.0, 0.0]), seen(5, [1.5, 0.12, 0.0])], 0.2)  # 12 cm: another branch
    assert len(tracks.tracks) == 2


def test_a_track_too_uncertain_to_fly_to_is_not_the_target():
    """From afar one view's depth σ is centimetres: three consistent views of σ 6 cm are not enough evidence
    for a target that must be within 5 cm; as views add up (each from a new viewpoint) σ falls under the
    bound and the track becomes the target."""
    cfg = TrackingConfig(target_min_observations=3, target_max_sigma_m=0.02, bias_share=0.0, process_noise_m2_per_s=0)
    tracks = WorldTracks(cfg, TargetRule(min_confidence=0.5))
    far = np.eye(3) * 0.06**2
    became = None
    for k in range(20):
        camera = np.array([0.0, 0.1 * k, 0.0])  # the vehicle moves: every view is a new viewpoint
        z = Measurement(0, np.array([2.8, 0.0, 0.0]), far, 0.9, camera)
        tracks.update([z], k / FPS)
        (track,) = tracks.tracks
        if tracks.target(k / FPS) is not None and became is None:
            became = k
        assert (tracks.target(k / FPS) is not None) == (track.sigma_m <= 0.02)
    # n views of σ 6 cm fuse to 6 / √n cm: 2 cm at the 9th view
    assert became == 8


def test_a_target_whose_sigma_grows_past_the_bound_loses_its_claim():
    cfg = TrackingConfig(target_min_observations=1, target_max_sigma_m=0.02, process_noise_m2_per_s=1e-3)
    tracks = WorldTracks(cfg, TargetRule(min_confidence=0.5, max_age_s=2.0))
    tracks.update([seen(0, [1.5, 0.0, 0.0])], 0.0)
    assert tracks.target(0.0) is not None
    # unseen for 0.4 s, a track drifting at 1e-3 m²/s has grown from σ 1 cm to ~2.2 cm: no longer the target
    tracks.update([], 0.4)
    assert tracks.target_id is None and tracks.target(0.4) is None
