"""The relay speaks real MAVLink 2 to a loopback peer: fields, units, frames, timing, staleness."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from mavlink_peer import LoopbackPeer, of_type
from result_factory import branch, frame_result

from branchrange.config.sections import MavlinkConfig, TrackingConfig
from branchrange.core.frame_result import FrameResult
from branchrange.onboard.mavlink import CameraMount, MavlinkRelay, messages

RESULT = frame_result(
    [branch(0, [0.1, -0.2, 1.4]), branch(3, [0.5, 0.25, 2.0]), branch(7, [-0.6, 0.1, 3.0])], target_id=0
)
MOUNT_XYZ = (0.2, 0.0, 0.05)


@pytest.fixture
def peer():
    p = LoopbackPeer()
    yield p
    p.close()


def relay_for(peer: LoopbackPeer, min_observations: int = 1, **overrides) -> MavlinkRelay:
    """A relay to `peer`; by default one result is evidence enough (these tests are about the messages)."""
    cfg = MavlinkConfig(url=f"udpout:127.0.0.1:{peer.port}", **overrides)
    tracking = TrackingConfig(target_min_observations=min_observations)
    return MavlinkRelay(cfg, CameraMount.from_rpy((0, 0, 0), MOUNT_XYZ), tracking=tracking)


def first_frame_after_publish(peer: LoopbackPeer, relay: MavlinkRelay, result: FrameResult):
    """Publish once and return the messages of the first frame set carrying the target."""
    relay.publish(result)
    got = peer.collect(2.0, until=lambda r: any(m.type == "DEBUG_VECT" and not math.isnan(m.msg.x) for m in r))
    vect = [m for m in of_type(got, "DEBUG_VECT") if not math.isnan(m.msg.x)][0]
    t = vect.msg.time_usec // 1000
    return [m for m in got if getattr(m.msg, "time_boot_ms", None) == t or m is vect]


def test_frame_messages_decode_with_body_frd_positions_and_centimetres(peer):
    with relay_for(peer) as relay:
        frame = first_frame_after_publish(peer, relay, RESULT)
    (dist,) = of_type(frame, "DISTANCE_SENSOR")
    obstacles = of_type(frame, "OBSTACLE_DISTANCE_3D")
    (vect,) = of_type(frame, "DEBUG_VECT")

    assert dist.msg.current_distance == round(math.dist((0, 0, 0), RESULT.branches[0].cut_point_m) * 100) == 142
    assert (dist.msg.min_distance, dist.msg.max_distance, dist.msg.covariance) == (20, 1000, 255)
    assert dist.msg.orientation == 100 and list(dist.msg.quaternion) == [1.0, 0.0, 0.0, 0.0]
    # the target (id 0) is not an obstacle by default; the others are, in body FRD plus the mount offset
    assert sorted(o.msg.obstacle_id for o in obstacles) == [3, 7]
    by_id = {o.msg.obstacle_id: o.msg for o in obstacles}
    np.testing.assert_allclose([by_id[3].x, by_id[3].y, by_id[3].z], [2.0 + 0.2, 0.5, 0.25 + 0.05], atol=1e-6)
    np.testing.assert_allclose([by_id[7].x, by_id[7].y, by_id[7].z], [3.0 + 0.2, -0.6, 0.1 + 0.05], atol=1e-6)
    assert all(
        o.msg.frame == 12 and o.msg.min_distance == pytest.approx(0.2) and o.msg.max_distance == 10.0 for o in obstacles
    )
    assert vect.msg.name == "CUT"
    np.testing.assert_allclose([vect.msg.x, vect.msg.y, vect.msg.z], [1.4 + 0.2, 0.1, -0.2 + 0.05], atol=1e-6)
    # one shared timestamp, all within 50 ms, MAVLink 2 from the onboard computer's ids
    assert (
        len({m.msg.time_boot_ms for m in [dist, *obstacles]}) == 1
        and vect.msg.time_usec == dist.msg.time_boot_ms * 1000
    )
    arrivals = [m.at for m in frame]
    assert max(arrivals) - min(arrivals) < 0.050
    assert all(m.msg.get_srcSystem() == 1 and m.msg.get_srcComponent() == 191 for m in frame)
    assert all(m.msg.get_msgbuf()[0] == 0xFD for m in frame)  # MAVLink 2 start byte


def test_the_targets_confidence_reaches_the_autopilot_as_signal_quality(peer):
    result = frame_result([branch(0, [0.1, -0.2, 1.4], confidence=0.834), branch(3, [0.5, 0.25, 2.0])], target_id=0)
    with relay_for(peer) as relay:
        frame = first_frame_after_publish(peer, relay, result)
    (dist,) = of_type(frame, "DISTANCE_SENSOR")
    assert (dist.msg.current_distance, dist.msg.signal_quality) == (142, 83)  # 0.834 → 83 %


@pytest.mark.parametrize("confidence, quality", [(1.0, 100), (0.7, 70), (0.005, 1), (0.0, 1), (0.996, 100), (0.024, 2)])
def test_signal_quality_is_the_confidence_in_percent_and_never_reads_as_unknown(confidence, quality):
    target = messages.BodyPoint(0, np.array([1.0, 0.0, 0.0]), confidence)
    assert messages.signal_quality(target) == quality
    assert messages.signal_quality(None) == 0  # no target: nothing measured, MAVLink's "unknown"


def test_target_as_obstacle_adds_it_and_uses_the_forward_orientation(peer):
    with relay_for(peer, target_as_obstacle=True) as relay:
        frame = first_frame_after_publish(peer, relay, RESULT)
    assert sorted(o.msg.obstacle_id for o in of_type(frame, "OBSTACLE_DISTANCE_3D")) == [0, 3, 7]
    (dist,) = of_type(frame, "DISTANCE_SENSOR")
    assert dist.msg.orientation == 0  # MAV_SENSOR_ROTATION_NONE: forward


def test_stale_result_becomes_no_target_and_sending_continues_at_the_rate(peer):
    with relay_for(peer, max_result_age_s=0.3, send_rate_hz=5.0) as relay:
        relay.publish(RESULT)
        got = peer.collect(1.5)
    dists = of_type(got, "DISTANCE_SENSOR")
    t0 = next(d.at for d in dists if d.msg.current_distance != 1001)  # sets before publish say "no target"
    fresh = [d for d in dists if 0 <= d.at - t0 < 0.25]
    stale = [d for d in dists if d.at - t0 > 0.45]
    assert fresh and all(d.msg.current_distance == 142 for d in fresh)
    assert stale and all(d.msg.current_distance == 1001 for d in stale)  # max_distance + 1: nothing in range
    assert all(d.msg.signal_quality == 100 for d in fresh) and all(d.msg.signal_quality == 0 for d in stale)
    gaps = np.diff([d.at for d in dists])
    assert gaps.max() < 0.35, f"sets must go out at >= 2 Hz without new results, longest gap {gaps.max():.3f} s"
    late_vects = [v for v in of_type(got, "DEBUG_VECT") if v.at - t0 > 0.45]
    assert late_vects and all(math.isnan(v.msg.x) for v in late_vects)
    late_obstacles = [o for o in of_type(got, "OBSTACLE_DISTANCE_3D") if o.at - t0 > 0.45]
    assert late_obstacles and all(o.msg.obstacle_id == 65535 and o.msg.x > o.msg.max_distance for o in late_obstacles)


def test_result_captured_too_long_ago_is_never_sent(peer):
    with relay_for(peer, max_result_age_s=0.3) as relay:
        relay.publish(RESULT, captured_at=time.monotonic() - 1.0)
        got = peer.collect(0.6)
    dists = of_type(got, "DISTANCE_SENSOR")
    assert dists and all(d.msg.current_distance == 1001 for d in dists)


def test_heartbeat_at_1hz_turns_critical_when_camera_is_lost(peer):
    with relay_for(peer) as relay:
        beats = of_type(peer.collect(2.3), "HEARTBEAT")
        relay.set_camera_lost(True)
        lost = of_type(peer.collect(0.3, until=lambda r: bool(of_type(r, "HEARTBEAT"))), "HEARTBEAT")
        assert relay.link_state()["camera_lost"] is True
    assert len(beats) == 3
    assert np.diff([b.at for b in beats]) == pytest.approx([1.0, 1.0], abs=0.1)
    hb = beats[0].msg
    assert (hb.type, hb.autopilot, hb.system_status, hb.mavlink_version) == (18, 8, 4, 3)
    assert lost and lost[0].msg.system_status == 5  # MAV_STATE_CRITICAL, sent at once


def test_unreachable_tcp_link_reports_down_without_raising():
    cfg = MavlinkConfig(url="tcp:127.0.0.1:1", reconnect_interval_s=0.1)
    with MavlinkRelay(cfg, CameraMount.from_rpy()) as relay:
        relay.publish(RESULT)
        time.sleep(0.3)
        state = relay.link_state()
    assert state["connected"] is False and state["frames_sent"] == 0
    assert "tcp:127.0.0.1:1" in state["last_error"] and state["send_errors"] > 0


def test_no_target_goes_out_while_the_camera_is_lost_however_fresh_the_result(peer):
    with relay_for(peer, send_rate_hz=10.0) as relay:
        relay.set_camera_lost(True)
        relay.publish(RESULT)  # a fresh result captured just now, e.g. the frame before the camera fell
        got = peer.collect(0.5)
        relay.set_camera_lost(False)
        relay.publish(RESULT)
        back = peer.collect(
            0.5, until=lambda r: any(d.msg.current_distance == 142 for d in of_type(r, "DISTANCE_SENSOR"))
        )
    dists = of_type(got, "DISTANCE_SENSOR")
    assert dists and all(d.msg.current_distance == 1001 for d in dists)
    assert all(math.isnan(v.msg.x) for v in of_type(got, "DEBUG_VECT"))
    # the other branches are still obstacles: the camera's last view of them is not a target, but they are there
    assert {o.msg.obstacle_id for o in of_type(got, "OBSTACLE_DISTANCE_3D")} >= {3, 7}
    assert any(d.msg.current_distance == 142 for d in of_type(back, "DISTANCE_SENSOR"))


def test_without_vehicle_state_a_target_needs_its_branch_in_results_in_a_row(peer):
    with relay_for(peer, min_observations=3, send_rate_hz=10.0) as relay:
        for _ in range(2):
            relay.publish(RESULT)
        early = peer.collect(0.3)
        relay.publish(frame_result([branch(3, [0.5, 0.25, 2.0])], target_id=3))  # branch 0 missing: count restarts
        relay.publish(RESULT)
        relay.publish(RESULT)
        gap = peer.collect(0.3)
        relay.publish(RESULT)  # the third in a row
        late = peer.collect(
            0.5, until=lambda r: any(d.msg.current_distance == 142 for d in of_type(r, "DISTANCE_SENSOR"))
        )
    assert all(d.msg.current_distance != 142 for d in of_type(early + gap, "DISTANCE_SENSOR"))
    assert any(d.msg.current_distance == 142 for d in of_type(late, "DISTANCE_SENSOR"))


def test_without_vehicle_state_a_target_too_far_for_one_view_is_withheld(peer):
    """One view's σ is all a camera-mode target has: at 2.5 m (f 700 px, B 63 mm) its depth σ is
    0.34 · 2.5² / (700 · 0.063) ≈ 4.8 cm, over `tracking.target_max_sigma_m` (2 cm): reported as a candidate,
    never the target; at 1.2 m (σ ≈ 1.1 cm) the same branch is the target."""
    far = frame_result([branch(5, [0.0, 0.1, 2.5])], target_id=5)
    near = frame_result([branch(5, [0.0, 0.1, 1.2])], target_id=5)
    with relay_for(peer, min_observations=1, send_rate_hz=10.0) as relay:
        relay.publish(far)
        withheld = peer.collect(0.4)
        relay.publish(near)
        sent = peer.collect(2.0, until=lambda r: any(not math.isnan(m.msg.x) for m in of_type(r, "DEBUG_VECT")))
    assert of_type(withheld, "DEBUG_VECT") and all(math.isnan(m.msg.x) for m in of_type(withheld, "DEBUG_VECT"))
    assert 5 in {o.msg.obstacle_id for o in of_type(withheld, "OBSTACLE_DISTANCE_3D")}  # still an obstacle
    assert any(not math.isnan(m.msg.x) for m in of_type(sent, "DEBUG_VECT"))
