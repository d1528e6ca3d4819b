"""The onboard daemon: camera source → pipeline → MAVLink relay + JSONL results log (+ API state).

One loop in one process. The source is drained by a capture thread (`LatestFrameSource`), so the
newest frame always wins and a slow pipeline never works on old frames. The loop
- processes each frame, publishes the result to the relay, writes one JSON line, keeps it for /latest;
- skips and logs a corrupt frame, and logs (does not die on) a frame the pipeline rejects;
- is the camera watchdog: no frame for `camera.stall_timeout_s` (or the source saying it is lost)
  marks the camera lost (HEARTBEAT CRITICAL, results go stale → "no target"); after three stall
  timeouts it closes the source and opens a fresh one, and forgets tracked branches;
- logs a status line (fps, latency, drops, camera, link) every `log.status_interval_s`;
- warns when a result is already older than `mavlink.max_result_age_s` when it is published: the
  relay then reports "no target" for it, so a pipeline that slow never gives the autopilot one.
`stop()` (the SIGTERM/SIGINT handler calls it) ends the loop within one stall timeout.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from branchrange.config import Config
from branchrange.frame_results import process_frame, result_line
from branchrange.mavlink import MavlinkRelay
from camera.sources import CorruptFrameError, LatestFrameSource, SourceDisconnected, SourceError, StereoSource

log = logging.getLogger("branchrange.daemon")
#: Stall timeouts without a frame after which the source is closed and opened again.
REOPEN_AFTER_STALLS = 3


class Daemon:
    """Runs the onboard loop; also the `LiveStatus` the API reads (`latest_result`, `health`)."""

    def __init__(self, cfg: Config, *, open_source: Callable[[], StereoSource], pipeline: Any,
                 relay: MavlinkRelay | None = None, results_path: str | Path | None = None,
                 metrics: Any = None, clock: Callable[[], float] = time.monotonic):
        self.cfg = cfg
        self._open_source = open_source
        self.pipeline = pipeline
        self.relay = relay
        self.metrics = metrics  # api.metrics.Metrics when the API runs in the same process
        self._clock = clock
        self._results: IO[str] | None = None
        if results_path:
            Path(results_path).parent.mkdir(parents=True, exist_ok=True)
            self._results = open(results_path, "a", encoding="utf-8", buffering=1)  # one flushed line per frame
        self._stop = threading.Event()
        self._latest: dict[str, Any] | None = None
        self.camera_lost = False
        self.frames = 0
        self.corrupt = 0
        self.rejected = 0
        self.reopens = 0
        self.dropped = 0
        self.late = 0  # results older than mavlink.max_result_age_s when published
        self._dropped_by_closed_sources = 0
        self._latencies: list[float] = []

    def latest_result(self) -> dict[str, Any] | None:
        """The newest frame's result (for GET /latest)."""
        return self._latest

    def health(self) -> dict[str, Any]:
        """Model, camera and link state (for GET /health)."""
        camera = {"source": self.cfg.camera.source, "lost": self.camera_lost, "frames": self.frames,
                  "dropped": self.dropped, "corrupt": self.corrupt, "reopens": self.reopens, "late": self.late}
        model = {"loaded": True, "backend": self.cfg.stereo.backend, "max_disp": self.cfg.stereo.max_disp}
        return {"model": model, "camera": camera,
                "mavlink": None if self.relay is None else self.relay.link_state()}

    def stop(self) -> None:
        """Ask the loop to finish (safe from a signal handler or another thread)."""
        self._stop.set()

    def _count_error(self, kind: str) -> None:
        if self.metrics is not None:
            self.metrics.count_error(kind)

    def _set_camera_lost(self, lost: bool) -> None:
        if lost != self.camera_lost:
            self.camera_lost = lost
            (log.warning if lost else log.info)("camera %s", "lost" if lost else "back")
            if lost:
                self._count_error("camera_lost")
            if self.relay is not None:
                self.relay.set_camera_lost(lost)

    def _process(self, frame: Any) -> None:
        """One frame through the pipeline to the relay, the log and /latest."""
        received = self._clock()
        try:
            result = process_frame(self.pipeline, frame)
        except ValueError as exc:
            self.rejected += 1
            self._count_error("rejected_frame")
            log.warning("frame %d rejected by the pipeline: %s", frame.index, exc)
            return
        if self.relay is not None:
            self.relay.publish(result, captured_at=received)
            self._check_age(self._clock() - received)
        if self._results is not None:
            self._results.write(result_line(result))
        self._latest = result
        self.frames += 1
        latency = self._clock() - received
        self._latencies.append(latency)
        if self.metrics is not None:
            self.metrics.observe_frame(latency, "daemon")

    def _check_age(self, age_s: float) -> None:
        """Count a result that was stale on publishing; warn on the first one."""
        if age_s <= self.cfg.mavlink.max_result_age_s:
            return
        self.late += 1
        if self.late == 1:
            log.warning("frame took %.0f ms, more than mavlink.max_result_age_s = %.0f ms: its result goes out as "
                        "'no target'; a faster stereo backend or smaller max_disp is needed for the autopilot to "
                        "get targets", 1000 * age_s, 1000 * self.cfg.mavlink.max_result_age_s)

    def _status(self, since: float, now: float, frames_then: int) -> None:
        fps = (self.frames - frames_then) / max(now - since, 1e-9)
        latency = 1000 * sum(self._latencies) / len(self._latencies) if self._latencies else 0.0
        self._latencies.clear()
        link = "off" if self.relay is None else ("up" if self.relay.link_state()["connected"] else "down")
        log.info("status frames=%d fps=%.1f latency_ms=%.0f dropped=%d corrupt=%d late=%d camera=%s link=%s",
                 self.frames, fps, latency, self.dropped, self.corrupt, self.late,
                 "lost" if self.camera_lost else "ok", link)

    def run(self, max_frames: int | None = None) -> int:
        """Process frames until the source ends, `max_frames` are done or `stop()`; returns frames done."""
        timeout = self.cfg.camera.stall_timeout_s
        source = self._try_open()
        stalls = 0
        status_at, frames_then = self._clock(), self.frames
        try:
            while not self._stop.is_set() and (max_frames is None or self.frames < max_frames):
                now = self._clock()
                if now - status_at >= self.cfg.log.status_interval_s:
                    self._status(status_at, now, frames_then)
                    status_at, frames_then = now, self.frames
                frame = None
                if source is None:
                    self._stop.wait(timeout)
                else:
                    try:
                        frame = source.get(timeout=timeout)
                    except StopIteration:
                        log.info("source ended")
                        break
                    except CorruptFrameError as exc:
                        self.corrupt += 1
                        self._count_error("corrupt_frame")
                        log.warning("corrupt frame skipped: %s", exc)
                        continue
                    except SourceDisconnected as exc:
                        log.warning("camera disconnected: %s", exc)
                if frame is None or source is None or source.is_lost:
                    self._set_camera_lost(True)
                    stalls += frame is None
                    if stalls >= REOPEN_AFTER_STALLS:
                        source, stalls = self._reopen(source), 0
                    if frame is None:
                        continue
                stalls = 0
                self._set_camera_lost(False)
                self.dropped = self._dropped_by_closed_sources + source.dropped
                self._process(frame)
        finally:
            if source is not None:
                source.close()
        self._status(status_at, self._clock(), frames_then)
        return self.frames

    def _try_open(self) -> LatestFrameSource | None:
        """A fresh source with its capture thread, or None (logged) when the camera cannot be opened."""
        try:
            return LatestFrameSource(self._open_source())
        except SourceError as exc:
            log.error("cannot open the camera: %s", exc)
            return None

    def _reopen(self, source: LatestFrameSource | None) -> LatestFrameSource | None:
        """Close a stalled source and open a fresh one; tracked branches are forgotten."""
        log.warning("no frame for %d stall timeouts: reopening the camera", REOPEN_AFTER_STALLS)
        if source is not None:
            source.close()
            self._dropped_by_closed_sources += source.dropped
        self.reopens += 1
        self.pipeline.reset()
        return self._try_open()

    def close(self) -> None:
        """Close the results log and the relay (the source is closed by `run`)."""
        if self.relay is not None:
            self.relay.close()
        if self._results is not None:
            self._results.close()
            self._results = None
