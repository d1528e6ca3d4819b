"""`MavlinkRelay`: turns per-frame results into MAVLink on a schedule the autopilot can rely on.

One background thread owns the link (pymavlink's sequence numbers and signing timestamps are not
thread-safe, and a reconnect must not race a send). It sends
- HEARTBEAT at 1 Hz, and at once when the camera-lost state changes (CRITICAL while lost);
- a frame's messages (DISTANCE_SENSOR, OBSTACLE_DISTANCE_3D…, DEBUG_VECT) as soon as `publish`
  hands over a result, back to back with one shared time_boot_ms;
- the same set at least `send_rate_hz` times a second between results, from the newest result
  while it is younger than `max_result_age_s` and as "no target" after that: autopilots call a
  silent sensor stale, and an old position must never be repeated as if it were current.
`publish` only stores the result and wakes the thread, so the pipeline never waits on the link.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from branchrange.config import MavlinkConfig
from branchrange.mavlink import messages
from branchrange.mavlink.connection import MavlinkLink, load_signing_key
from branchrange.mavlink.frames import CameraMount

HEARTBEAT_PERIOD_S = 1.0
#: How often the link thread looks for incoming messages when nothing else is due.
POLL_PERIOD_S = 0.05


class MavlinkRelay:
    """Sends BranchRange results to a flight controller; see the module docstring for timing."""

    def __init__(self, cfg: MavlinkConfig, mount: CameraMount, *,
                 clock: Callable[[], float] = time.monotonic):
        self._cfg = cfg
        self._mount = mount
        self._clock = clock
        key = load_signing_key(cfg.signing_key_file) if cfg.signing_key_file else None
        self._cond = threading.Condition()
        self._latest: tuple[Mapping[str, Any], float] | None = None
        self._new_result = False
        self._camera_lost = False
        self._lost_changed = False
        self._stopped = False
        self._boot = clock()
        self._last_time_boot_ms = -1
        self.frames_sent = 0
        self.no_target_frames = 0
        self._link = MavlinkLink(cfg.url, baud=cfg.baud, source_system=cfg.system_id,
                                 source_component=cfg.component_id, signing_key=key,
                                 reconnect_interval_s=cfg.reconnect_interval_s, clock=clock)
        self._thread = threading.Thread(target=self._run, name="mavlink-relay", daemon=True)
        self._thread.start()

    def publish(self, result: Mapping[str, Any], captured_at: float | None = None) -> None:
        """Hand over a frame's result; `captured_at` (the relay's clock, s) defaults to now."""
        with self._cond:
            self._latest = (result, self._clock() if captured_at is None else captured_at)
            self._new_result = True
            self._cond.notify()

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
        state.update(frames_sent=self.frames_sent, no_target_frames=self.no_target_frames,
                     camera_lost=self._camera_lost)
        return state

    def close(self) -> None:
        """Stop the thread and close the link; idempotent."""
        with self._cond:
            self._stopped = True
            self._cond.notify()
        self._thread.join(timeout=5.0)
        self._link.close()

    def __enter__(self) -> "MavlinkRelay":
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
                timeout = min(next_heartbeat, next_frame, self._clock() + POLL_PERIOD_S) - self._clock()
                if not (self._stopped or self._new_result or self._lost_changed) and timeout > 0:
                    self._cond.wait(timeout)
                if self._stopped:
                    return
                new_result, self._new_result = self._new_result, False
                lost_changed, self._lost_changed = self._lost_changed, False
                latest, camera_lost = self._latest, self._camera_lost
            now = self._clock()
            if lost_changed or now >= next_heartbeat:
                self._link.send([messages.heartbeat(camera_lost)])
                next_heartbeat = now + HEARTBEAT_PERIOD_S
            if new_result or now >= next_frame:
                self._send_frame(latest, now)
                next_frame = now + frame_period
            self._link.poll()

    def _send_frame(self, latest: tuple[Mapping[str, Any], float] | None, now: float) -> None:
        """Send the newest result's messages, or "no target" when there is none or it is stale."""
        fresh = latest is not None and now - latest[1] <= self._cfg.max_result_age_s
        result = latest[0] if fresh else None
        frame = messages.frame_messages(result, self._mount, self._cfg, self._time_boot_ms(now))
        if self._link.send(frame):
            self.frames_sent += 1
            self.no_target_frames += messages.target_branch(result) is None
