"""`MavlinkRelay`: turns per-frame results into MAVLink on a schedule the autopilot can rely on.

One background thread owns the link (pymavlink's sequence numbers and signing timestamps are not
thread-safe, and a reconnect must not race a send). It sends
- HEARTBEAT at 1 Hz, and at once when the camera-lost state changes (CRITICAL while lost);
- a frame's messages (DISTANCE_SENSOR, OBSTACLE_DISTANCE_3D…, DEBUG_VECT) as soon as `publish`
  hands over a result, back to back with one shared time_boot_ms;
- the same set at least `send_rate_hz` times a second between results: autopilots call a silent
  sensor stale.

One freshness rule for the target, in both modes below: a target goes out only while the cut point
it comes from was captured within `max_result_age_s` of the send and the camera is not lost; else
the set says "no target" (an old position must never be repeated as if it were current, and a late
result is not made current by fusing it). Obstacles follow the same rule without vehicle state; with
it, fused obstacles stay while their track is fresh (`tracking.stale_after_s`: the branch is still
there in the world, only its image is late).
`publish` never waits on the link: it stores the result, fuses it into the world tracks (no I/O,
well under a millisecond) and wakes the thread.

Vehicle state (see `vehicle_state`, `world_tracks`): once the autopilot's HEARTBEAT arrives the
thread asks it for ATTITUDE and LOCAL_POSITION_NED at `state_rate_hz` (again every second until
they flow) and keeps their history. `publish(result, captured_at)` carries each cut point camera →
body (mount) → local NED with the pose interpolated at `captured_at`, and fuses it into a track.
Each send then re-expresses the fresh tracks in the body frame of *now* (the newest pose,
extrapolated to the send time): the autopilot gets where the branch is at that moment, not where
it was at capture (latency compensation). In this "world" mode the target is the track chosen on
evidence with hysteresis (`world_tracks`: consistent observations, recency-weighted confidence, a
switching margin). Without a pose now, or
for a result captured when there was none, the relay behaves as without vehicle state ("camera"
mode: the result's cut points through the mount, valid for `max_result_age_s`); when vehicle state
comes (again), camera mode goes on until `tracking.target_min_observations` results in a row were
fused, so the target does not pause while the world tracks gather their evidence; `link_state()`
says which mode is in use. `targets()` gives the fused tracks for /latest and the results log.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from branchrange.config.sections import MavlinkConfig, TrackingConfig
from branchrange.core.cutpoints import DEFAULT_TARGET_POLICY, CutPointConfig
from branchrange.core.frame_result import FrameResult, WorldTargets
from branchrange.onboard.mavlink import messages
from branchrange.onboard.mavlink.approach import ApproachPlanner
from branchrange.onboard.mavlink.connection import MavlinkLink, load_signing_key
from branchrange.onboard.mavlink.frames import CameraMount, quaternion_wxyz
from branchrange.onboard.mavlink.vehicle_state import VehicleState
from branchrange.onboard.mavlink.world_tracks import (
    Measurement,
    TargetRule,
    WorldTracks,
    measurement_covariance,
    one_view_sigma_m,
)

log = logging.getLogger("branchrange.mavlink")
HEARTBEAT_PERIOD_S = 1.0
#: How often the link thread reads incoming messages while an autopilot is connected: a state
#: message's receive time is its arrival time within this, which the clock offset's minimum filters.
POLL_PERIOD_S = 0.01
#: ... and while none is (only its first HEARTBEAT is awaited; saves the CPU a 100 Hz loop costs).
IDLE_POLL_PERIOD_S = 0.05
#: MAVLink ids of the streams requested from the autopilot.
ATTITUDE_ID, LOCAL_POSITION_NED_ID = 30, 32
#: Ask for the streams again when no state message arrived for this long (s).
STATE_REQUEST_PERIOD_S = 1.0


class MavlinkRelay:
    """Sends BranchRange results to a flight controller; see the module docstring for timing."""

    def __init__(
        self,
        cfg: MavlinkConfig,
        mount: CameraMount,
        *,
        tracking: TrackingConfig = TrackingConfig(),
        target_policy: str = DEFAULT_TARGET_POLICY,
        target_min_confidence: float = CutPointConfig.target_min_confidence,
        clock: Callable[[], float] = time.monotonic,
    ):
        """`target_policy` and `target_min_confidence` are `[cutpoints]`'s: the fused target is ranked
        and gated as the per-frame one is."""
        self._cfg = cfg
        self._mount = mount
        self._tracking = tracking
        self._clock = clock
        key = load_signing_key(cfg.signing_key_file) if cfg.signing_key_file else None
        self._cond = threading.Condition()
        self._latest: tuple[FrameResult, float] | None = None
        self._new_result = False
        self._camera_lost = False
        self._lost_changed = False
        self._stopped = False
        self._boot = clock()
        self._last_time_boot_ms = -1
        self.frames_sent = 0
        self.no_target_frames = 0
        self.setpoints_sent = 0
        self.interval_acks = 0
        self.unfused_results = 0
        # vehicle state, tracks and the mode: written by the link thread and `publish`, read by both
        # and by `link_state`/`targets`; held only for computation, never across link I/O
        self._state_lock = threading.Lock()
        self._vehicle = VehicleState(max_extrapolation_s=cfg.pose_timeout_s)
        self._tracks = WorldTracks(tracking, TargetRule(target_policy, target_min_confidence, cfg.max_result_age_s))
        self._approach = ApproachPlanner(cfg)
        self._latest_fused = False
        # camera mode's evidence rule: results in a row that held each branch id (the pipeline's stable ids)
        self._seen_in_a_row: dict[int, int] = {}
        self._latest_evidenced = False
        self._fused_in_a_row = 0  # results fused in a row: the world tracks' evidence since vehicle state came
        self._mode: str | None = None  # "world" or "camera" from the first send on
        self._last_state_request = -math.inf
        self._link = MavlinkLink(
            cfg.url,
            baud=cfg.baud,
            source_system=cfg.system_id,
            source_component=cfg.component_id,
            signing_key=key,
            reconnect_interval_s=cfg.reconnect_interval_s,
            heartbeat_timeout_s=cfg.heartbeat_timeout_s,
            clock=clock,
        )
        self._thread = threading.Thread(target=self._run, name="mavlink-relay", daemon=True)
        self._thread.start()

    def publish(self, result: FrameResult, captured_at: float | None = None) -> None:
        """Hand over a frame's result; `captured_at` (the relay's clock, s) defaults to now."""
        captured_at = self._clock() if captured_at is None else captured_at
        fused = self._fuse(result, captured_at)
        self._seen_in_a_row = {b.id: self._seen_in_a_row.get(b.id, 0) + 1 for b in result.branches}
        evidenced = result.target_id is not None and (
            self._seen_in_a_row[result.target_id] >= self._tracking.target_min_observations
            and self._one_view_certain(result, result.target_id)
        )
        with self._cond:
            self._latest = (result, captured_at)
            self._latest_fused = fused
            self._latest_evidenced = evidenced
            self._new_result = True
            self._cond.notify()

    def _one_view_certain(self, result: FrameResult, branch_id: int) -> bool:
        """Whether branch `branch_id`'s cut point, from this one view, is known to `tracking.target_max_sigma_m`:
        without vehicle state nothing is fused, so one view's σ is all a camera-mode target has (its depth σ
        grows with the square of the range: ~5 cm at 2.5 m with the built-in segmenter at HD720)."""
        branch = next(b for b in result.branches if b.id == branch_id)
        sigma = one_view_sigma_m(
            np.asarray(branch.cut_point_m),
            self._tracking,
            result.camera.focal_px,
            result.camera.baseline_m,
            branch.disparity_scale or 1,
        )
        return sigma <= self._tracking.target_max_sigma_m

    def _fuse(self, result: FrameResult, captured_at: float) -> bool:
        """Fuse the result's cut points into the world tracks; False when there is no pose at capture."""
        with self._state_lock:
            pose = self._vehicle.pose_at(captured_at)
            if pose is None:
                self.unfused_results += self._vehicle.has_state
                self._fused_in_a_row = 0
                return False
            self._fused_in_a_row += 1
            cam_to_ned = pose.rotation @ self._mount.camera_to_body
            camera_m = pose.body_to_ned(self._mount.translation_m)
            measurements = [
                Measurement(
                    b.id,
                    pose.body_to_ned(self._mount.to_body(np.asarray(b.cut_point_m))),
                    measurement_covariance(
                        np.asarray(b.cut_point_m),
                        cam_to_ned,
                        self._tracking,
                        result.camera.focal_px,
                        result.camera.baseline_m,
                        b.disparity_scale or 1,
                    ),
                    b.confidence,
                    camera_m,
                    b.diameter_m,
                    light_allows_target=not b.light_refuses_target,
                )
                for b in result.branches
            ]
            self._tracks.update(measurements, captured_at)
            return True

    def vehicle_pose(self) -> tuple[tuple[float, float, float], tuple[float, float, float, float]] | None:
        """The vehicle's pose now, for viewers: (position local NED m, attitude quaternion w, x, y, z of
        body FRD → NED), or None without vehicle state."""
        pose = self._vehicle.pose_at(self._clock())
        if pose is None:
            return None
        return (float(pose.position_m[0]), float(pose.position_m[1]), float(pose.position_m[2])), quaternion_wxyz(
            pose.rotation
        )

    def targets(self) -> WorldTargets:
        """The fused tracks for /latest and the results log: local NED metres, 1-σ radius, age, count.

        `frame` is "local_ned" while vehicle state is in use, "camera" when results go out in the
        camera frame of their capture (then `tracks` is empty or holds tracks from before).
        """
        now = self._clock()
        with self._state_lock:
            target = self._tracks.target(now)
            return WorldTargets(
                frame="local_ned" if self._mode == "world" else "camera",
                target_track_id=None if target is None else target.track_id,
                tracks=tuple(t.summary(now) for t in self._tracks.fresh(now)),
            )

    def set_camera_lost(self, lost: bool) -> None:
        """Mark the camera lost (HEARTBEAT CRITICAL) or back; a heartbeat goes out at once."""
        with self._cond:
            if lost != self._camera_lost:
                self._camera_lost = lost
                self._lost_changed = True
                self._cond.notify()

    def link_state(self) -> dict[str, Any]:
        """Link and sending facts for /health and the daemon's status line."""
        state = self._link.state()
        now = self._clock()
        with self._state_lock:
            vehicle = self._vehicle.state(now)
            tracks = len(self._tracks.fresh(now))
        state.update(
            frames_sent=self.frames_sent,
            no_target_frames=self.no_target_frames,
            camera_lost=self._camera_lost,
            mode=self._mode or "camera",
            vehicle_state=vehicle,
            tracks=tracks,
            setpoints_sent=self.setpoints_sent,
            message_interval_acks=self.interval_acks,
            unfused_results=self.unfused_results,
        )
        return state

    def close(self) -> None:
        """Stop the thread and close the link; idempotent."""
        with self._cond:
            self._stopped = True
            self._cond.notify()
        self._thread.join(timeout=5.0)
        self._link.close()

    def __enter__(self) -> MavlinkRelay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _time_boot_ms(self, now: float) -> int:
        """Milliseconds since the relay started, strictly increasing so each frame's set is new."""
        ms = max(int((now - self._boot) * 1000), self._last_time_boot_ms + 1)
        self._last_time_boot_ms = ms
        return ms

    def _run(self) -> None:
        """The link thread: heartbeats, frame sets and reading, until `close`.

        State is taken under the lock, link I/O happens outside it: a slow reconnect must not
        block `publish` (the pipeline's thread).
        """
        next_heartbeat = next_frame = self._clock()
        frame_period = 1.0 / self._cfg.send_rate_hz
        while True:
            with self._cond:
                poll_period = POLL_PERIOD_S if self._link.connected else IDLE_POLL_PERIOD_S
                timeout = min(next_heartbeat, next_frame, self._clock() + poll_period) - self._clock()
                if not (self._stopped or self._new_result or self._lost_changed) and timeout > 0:
                    self._cond.wait(timeout)
                if self._stopped:
                    return
                new_result, self._new_result = self._new_result, False
                lost_changed, self._lost_changed = self._lost_changed, False
                latest, camera_lost, fused = self._latest, self._camera_lost, self._latest_fused
                evidenced = self._latest_evidenced
            self._receive(self._link.poll(), self._clock())
            now = self._clock()
            if lost_changed or now >= next_heartbeat:
                self._link.send([messages.heartbeat(camera_lost)])
                next_heartbeat = now + HEARTBEAT_PERIOD_S
            self._request_state(now)
            if new_result or now >= next_frame:
                self._send_frame(latest, fused, camera_lost, evidenced, now)
                next_frame = now + frame_period

    def _receive(self, received: list[Any], now: float) -> None:
        """Take the autopilot's state messages and command acks (others' messages are ignored)."""
        with self._state_lock:
            for msg in received:
                if not self._link.from_peer(msg):
                    continue
                if msg.get_type() == "COMMAND_ACK" and msg.command == messages.MAV_CMD_SET_MESSAGE_INTERVAL:
                    self.interval_acks += msg.result == 0  # MAV_RESULT_ACCEPTED
                else:
                    self._vehicle.handle(msg, now)

    def _request_state(self, now: float) -> None:
        """Ask the connected autopilot for ATTITUDE and LOCAL_POSITION_NED while they do not flow."""
        if not (self._cfg.request_vehicle_state and self._link.connected):
            return
        newest = self._vehicle.newest_sample_time
        flowing = newest is not None and now - newest < STATE_REQUEST_PERIOD_S
        if flowing or now - self._last_state_request < STATE_REQUEST_PERIOD_S:
            return
        self._last_state_request = now
        peer = self._link.peer
        if peer is None:  # connected implies a peer; a disconnect between the two reads leaves none
            return
        self._link.send(
            [
                messages.message_interval_request(i, self._cfg.state_rate_hz, peer.system_id, peer.component_id)
                for i in (ATTITUDE_ID, LOCAL_POSITION_NED_ID)
            ]
        )

    def _frame_targets(
        self, latest: tuple[FrameResult, float] | None, fused: bool, camera_lost: bool, evidenced: bool, now: float
    ) -> tuple[messages.FrameTargets, tuple[Any, float] | None]:
        """This send's targets in the body frame of `now`, and the approach setpoint (or None).

        No target while the camera is lost, whatever the tracks or the newest result say: what the
        relay last saw may be the frame before a fall or a cover. Without vehicle state the newest
        result's target goes out only once `evidenced`: its branch id was in the last
        `tracking.target_min_observations` results in a row (the world tracks' rule, on the pipeline's ids)
        and its one view's σ is within `tracking.target_max_sigma_m` (the world tracks' bound, unfused).
        Hand-over: when vehicle state comes (at start, after the link was lost), camera mode goes on until
        that many results in a row were fused — the world tracks have had the observations their evidence
        rule needs; switching at the first fused one left "no target" for as many results (seconds on a
        busy machine) while the camera rule had its evidence."""
        with self._state_lock:
            pose = self._vehicle.pose_at(now)
            fresh_unfused = latest is not None and not fused and now - latest[1] <= self._cfg.max_result_age_s
            handing_over = self._mode != "world" and self._fused_in_a_row < self._tracking.target_min_observations
            if pose is not None and not fresh_unfused and not handing_over:
                self._set_mode("world")
                target = None if camera_lost else self._tracks.target(now)
                points = [
                    messages.BodyPoint(t.track_id, pose.ned_to_body(t.position_m), t.confidence)
                    for t in self._tracks.fresh(now)
                ]
                body_target = next((p for p in points if target is not None and p.id == target.track_id), None)
                peer = self._link.peer if self._link.connected else None
                return messages.FrameTargets(body_target, points), self._approach.setpoint(target, pose, peer, now)
            self._set_mode("camera")
            self._approach.reset()  # no setpoint without a pose
        fresh = latest[0] if latest is not None and now - latest[1] <= self._cfg.max_result_age_s else None
        targets = messages.targets_from_result(fresh, self._mount)
        withheld = camera_lost or not evidenced
        return (messages.FrameTargets(None, targets.candidates) if withheld else targets), None

    def _set_mode(self, mode: str) -> None:
        """Switch between "world" and "camera" sending, and say so in the log."""
        if mode == self._mode:
            return
        previous, self._mode = self._mode, mode
        if mode == "world":
            log.info(
                "vehicle state from the autopilot: targets fused in local NED, sent in the body frame of each send"
            )
        else:  # a warning when the pose was lost, news at start-up (the autopilot may not have answered yet)
            (log.warning if previous == "world" else log.info)(
                "no vehicle state from the autopilot: targets go out in the body frame of their capture, "
                "without latency compensation"
            )

    def _send_frame(
        self, latest: tuple[FrameResult, float] | None, fused: bool, camera_lost: bool, evidenced: bool, now: float
    ) -> None:
        """Send this moment's targets (world tracks, else the newest fresh result, else "no target")."""
        targets, setpoint = self._frame_targets(latest, fused, camera_lost, evidenced, now)
        time_boot_ms = self._time_boot_ms(now)
        frame = messages.frame_messages(targets, self._mount, self._cfg, time_boot_ms, self._tracking.gate_m)
        if self._link.send(frame):
            self.frames_sent += 1
            self.no_target_frames += targets.target is None
        if setpoint is not None and self._link.peer is not None:
            peer = self._link.peer
            msg = messages.position_target(setpoint[0], setpoint[1], time_boot_ms, peer.system_id, peer.component_id)
            self.setpoints_sent += self._link.send([msg])
