"""The onboard daemon: camera source → pipeline → MAVLink relay + JSONL results log (+ API state).

Three threads, so no stage waits for a slower one and every stage works on the newest input.
The JSONL results log starts each run with a run header line (`frame_results.run_header`), so a
restart is visible in the log, and a reopened camera (whose indices and timestamps start again) gets
a camera-reopened marker line before its first result (`frame_results.camera_reopened_line`). Past
`log.results_max_mb` the log is rotated (`results_log.ResultsLog`, `log.results_keep` older files kept),
each new file starting with the run header again. Threads:
- **capture** (`LatestFrameSource`): drains the camera; the newest frame wins, older ones are
  dropped and counted (`dropped`; frames a paced replay dropped before releasing them, as too late to
  keep its schedule, in `dropped_late`); each frame is stamped with its arrival time on the monotonic
  clock. The capture time every age and latency is measured from is the frame's own `timestamp_ns`
  when it is on this machine's monotonic clock (live sources stamp frames so: no later than the
  arrival, at most `CAPTURE_CLOCK_WINDOW_S` before it), else the arrival (a replay's recorded times):
  a frame that arrives late — buffered by the driver, held back — must not count as new;
- **stereo** (the `run()` thread): on the first frame of each opened camera, a check that the
  rectified rows are aligned (`branchrange.core.pair_check`: a warning with the fix when not); then
  rectification and disparity (`Pipeline.stereo_stage`; in
  `stereo.mode = "roi"` the coarse pass, the segmenter and the full-resolution regions); it is
  also the camera watchdog: no frame for `camera.stall_timeout_s` (from the newest frame's arrival, however
  long its processing took), the source saying it is lost,
  or `CORRUPT_FRAMES_LOST` unreadable frames in a row mark the camera lost (HEARTBEAT CRITICAL,
  results go stale → "no target"); after three stall timeouts it closes the source, opens a fresh
  one and forgets tracked branches; a camera that cannot be opened (unplugged) is tried again every
  stall timeout, so it is back within one of being plugged in (its error is logged once per outage).
  A frame whose `timestamp_ns` is not newer than the previous frame's from the same opened camera
  (a frozen driver buffer delivering one image again, frames arriving out of order) is skipped and
  counted (`repeated`): it would pass an old image off as fresh, and the tracker must never go back
  in time. With `stereo.workers` other than 1 this thread only dispatches: each frame goes to the next free
  stereo worker process (`stereo_workers`, started with the run and warmed on its first frame or by
  `warm_up`), whose outputs come back in capture order; a dead worker's frame counts as dropped;
- **geometry + send** (a worker): masks, cut points, tracking, target (`Pipeline.geometry_stage`; with stereo
  workers, which find the masks and cut points themselves, only its end, `Pipeline.finish_frame`) on the newest
  stereo output (one slot: an output the worker had no time for is replaced by the
  next and counted in `skipped`), then the relay (whose own thread sends on a fixed schedule and
  never waits for either), the JSONL log, /latest and the observers.
Each result carries `latency` (ms from capture to the stereo stage, to the geometry stage, to
publishing), besides the per-stage `timing_ms`. A result already older than
`mavlink.max_result_age_s` when published is counted (`late`) and goes out as "no target"; as ages
near that limit the daemon sheds work (`load_shedding`: the roi mode's full-resolution instances, then
the branches' refinement), gives it back when calm, and says so in the log, the status line (`shed=`)
and /health (`shedding`). After
the first `WARMUP_FRAMES` frames the daemon logs, once, whether its measured capture → publish
time can meet `max_result_age_s`, and what to change when it cannot. When the learned segmenter
measures the light of a frame in another class than the last (`branchrange.core.light_check`: dark,
bright, noisy, normal), the log says so: a warning out of normal light. A status line (fps, latency,
drops, camera, link) every `log.status_interval_s`. `stop()` (the SIGTERM/SIGINT handler calls
it) ends the loop within one stall timeout.
"""

from __future__ import annotations

import logging
import statistics
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

from branchrange.config.loader import Config
from branchrange.core.frame_result import FrameResult, Freshness, Latency
from branchrange.core.frame_results import camera_reopened_line, result_line, run_header_line, stereo_stage, utc_now
from branchrange.core.pair_check import check_rectification
from branchrange.onboard.load_shedding import LoadShedder
from branchrange.onboard.mavlink import CameraMount, MavlinkRelay
from branchrange.onboard.newest_slot import NewestSlot
from branchrange.onboard.results_log import ResultsLog
from branchrange.onboard.stereo_workers import StereoWorkers, WorkerOutput, worker_count
from camera.sources import CorruptFrameError, LatestFrameSource, SourceDisconnected, SourceError, StereoSource
from stereo.backends.base import validate_pair

log = logging.getLogger("branchrange.daemon")
#: Stall timeouts without a frame after which the source is closed and opened again.
REOPEN_AFTER_STALLS = 3
#: Unreadable frames in a row after which the camera counts as lost (a vanished recording, a dying cable).
CORRUPT_FRAMES_LOST = 5
#: Frames after which the measured capture → publish time is compared with `max_result_age_s`.
WARMUP_FRAMES = 3
#: A frame's `timestamp_ns` is taken as its capture time when it is at most this long (s) before its arrival.
CAPTURE_CLOCK_WINDOW_S = 5.0
#: The least the stereo thread waits for a frame (s), even when the stall timeout since the newest frame has
#: passed: the capture thread may have had no CPU (nor the interpreter lock) while this one worked, and must
#: get the chance to hand over a frame that is there (without it a loaded CPU made "camera lost" blips).
STALL_GRACE_S = 0.2


def capture_time(frame: Any, arrived: float) -> float:
    """When `frame` was captured (monotonic s): its own timestamp when that is on this machine's monotonic
    clock (no later than `arrived`, at most `CAPTURE_CLOCK_WINDOW_S` before it), else its arrival."""
    stamped = frame.timestamp_ns / 1e9
    return stamped if 0.0 <= arrived - stamped <= CAPTURE_CLOCK_WINDOW_S else arrived


def relay_for(cfg: Config, mount: CameraMount, relay_type: type[MavlinkRelay] = MavlinkRelay) -> MavlinkRelay:
    """The relay `cfg` asks for: its `[mavlink]` link, `[tracking]` fusion, and `[cutpoints]`' policy and
    minimum confidence, so the fused target is ranked and gated as the per-frame one is. `relay_type` lets
    a test or benchmark use a subclass that notes more."""
    return relay_type(
        cfg.mavlink,
        mount,
        tracking=cfg.tracking,
        target_policy=cfg.cutpoints.target_policy,
        target_min_confidence=cfg.cutpoints.target_min_confidence,
    )


#: Called once per processed frame with its `FrameResult` and the pipeline's `FrameArtifacts`.
ResultObserver = Callable[[FrameResult, Any], None]


class DaemonMetrics(Protocol):
    """What the daemon reports to a metrics registry (`api.metrics.Metrics` when the API runs in the
    same process); declared here so the onboard layer does not import the API above it."""

    def observe_frame(self, seconds: float, source: str) -> None:
        """One published frame, `seconds` from capture to publishing; `source` labels who processed it."""

    def count_error(self, kind: str) -> None:
        """One error of `kind` (e.g. 'camera_lost')."""


@dataclass(frozen=True, eq=False)
class _StereoOutput:
    """A frame between the two halves: the stereo stage's output (`Pipeline.stereo_stage`), or with
    `cut_points_done` a stereo worker's (`Pipeline.cut_point_stage`); when the frame was captured, its stereo half
    started and ended (monotonic s)."""

    stage: Any
    captured_at: float
    stereo_started_at: float
    stereo_done_at: float
    cut_points_done: bool = False


class Daemon:
    """Runs the onboard loop; also the `LiveStatus` the API reads (`latest_result`, `health`)."""

    def __init__(
        self,
        cfg: Config,
        *,
        open_source: Callable[[], StereoSource],
        pipeline: Any,
        relay: MavlinkRelay | None = None,
        results_path: str | Path | None = None,
        metrics: DaemonMetrics | None = None,
        observers: Sequence[ResultObserver] = (),
        pipeline_factory: Callable[[], Any] | None = None,
    ):
        self.cfg = cfg
        self._open_source = open_source
        self.pipeline = pipeline
        self.relay = relay
        self.metrics = metrics
        self.observers = list(observers)
        self._results: ResultsLog | None = None
        if results_path:
            # a restart appends to the same log: each run starts with its header, never silently at frame 0 again
            self._results = ResultsLog(
                results_path,
                run_header_line("daemon", cfg, cfg.camera.source),
                max_bytes=cfg.log.results_max_bytes,
                keep=cfg.log.results_keep,
            )
        self.shedder = LoadShedder(cfg.shedding, cfg.mavlink.max_result_age_s)
        self._stop = threading.Event()
        self._latest: tuple[FrameResult, float] | None = None  # and when its frame arrived (monotonic s)
        self._slot = NewestSlot()
        self._counts_lock = threading.Lock()
        self.camera_lost = False
        self.frames = 0
        self.corrupt = 0
        self.rejected = 0
        self.reopens = 0
        self._camera_dropped = 0  # by the open source and those closed before it
        self.dropped_late = 0
        self.late = 0  # results older than mavlink.max_result_age_s when published
        self.repeated = 0  # frames skipped: captured no later than the frame before them
        self._repeat_logged_for = -1  # the reopening count when a repeated frame was last logged
        self._newest_capture_ns: int | None = None  # the newest frame's timestamp, of the open camera
        self._dropped_by_closed_sources = 0
        self._dropped_late_by_closed_sources = 0
        self._corrupt_in_a_row = 0
        self._latencies: list[float] = []
        self._warmup: list[tuple[float, float, float]] = []  # (capture → publish, stereo, geometry) s
        self._speed_reported = False
        self._pair_checked = False
        self._speed_warned = False
        self._light: str | None = None  # the class of light of the last result that measured it
        # (reason, reopens, UTC) of a camera reopening whose marker goes into the log before the next result
        self._reopened: tuple[str, int, str] | None = None
        self._pipeline_factory = pipeline_factory
        self.workers = self._worker_count()
        self._pool: StereoWorkers | None = None
        self._warmed = False  # whether the workers ran a first frame (`StereoWorkers.warm`)

    def _worker_count(self) -> int:
        """How many processes run the stereo stage (`stereo.workers`; 1: the run() thread itself)."""
        count = worker_count(self.cfg.stereo.workers)
        if count > 1 and self.cfg.roi.keyframe_interval_s > 0:
            log.warning(
                "stereo.workers = %d ignored: with keyframes (roi.keyframe_interval_s = %g) each frame carries "
                "the last frame's instances, so the stereo stage runs in one thread",
                self.cfg.stereo.workers,
                self.cfg.roi.keyframe_interval_s,
            )
            return 1
        if count > 1 and self._pipeline_factory is None:
            raise ValueError(f"stereo.workers = {self.cfg.stereo.workers} needs a pipeline_factory for its workers")
        return count

    @property
    def dropped(self) -> int:
        """Frames never processed: those the camera source dropped (the stereo stage had no time for them)
        and those a stereo worker took with it when it died."""
        return self._camera_dropped + (0 if self._pool is None else self._pool.lost)

    @property
    def skipped(self) -> int:
        """Stereo outputs replaced before the geometry stage took them (it was busy with an older one)."""
        return self._slot.replaced

    def latest_result(self) -> FrameResult | None:
        """The newest frame's result with its `freshness` now (for GET /latest): the age since its frame
        arrived, and `stale` past `mavlink.max_result_age_s` — a stalled camera leaves the last result
        served, and this is how a reader tells it is old."""
        latest = self._latest
        if latest is None:
            return None
        result, captured_at = latest
        age_s = time.monotonic() - captured_at
        limit = self.cfg.mavlink.max_result_age_s
        return replace(result, freshness=Freshness(round(age_s, 3), age_s > limit, limit))

    def health(self) -> dict[str, Any]:
        """Model, camera and link state (for GET /health); the model's state includes the last frame's
        out-of-distribution reading (`FrameResult.segmenter_ood`: score and flag; None without one)."""
        camera = {
            "source": self.cfg.camera.source,
            "lost": self.camera_lost,
            "frames": self.frames,
            "dropped": self.dropped,
            "dropped_late": self.dropped_late,
            "skipped": self.skipped,
            "corrupt": self.corrupt,
            "reopens": self.reopens,
            "late": self.late,
            "repeated": self.repeated,
        }
        pool = self._pool
        workers = {
            "count": self.workers,
            "restarts": 0 if pool is None else pool.restarts,
            "lost_frames": 0 if pool is None else pool.lost,
        }
        latest = self._latest
        ood = None if latest is None else latest[0].segmenter_ood  # the last frame's: does the model know it?
        model = {
            "loaded": True,
            "backend": self.cfg.stereo.backend,
            "max_disp": self.cfg.stereo.max_disp,
            "mode": self.cfg.stereo.mode,
            "segmenter_ood_score": None if ood is None else ood.score,
            "segmenter_ood_flagged": None if ood is None else ood.flagged,
        }
        return {
            "model": model,
            "camera": camera,
            "stereo_workers": workers,
            "shedding": self.shedder.state(),
            "mavlink": None if self.relay is None else self.relay.link_state(),
        }

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

    def _reject(self, index: int, error: Exception) -> None:
        with self._counts_lock:
            self.rejected += 1
        self._count_error("rejected_frame")
        if isinstance(error, ValueError):
            log.warning("frame %d rejected by the pipeline: %s", index, error)
        else:  # a bug, not bad input: keep flying, but leave the traceback in the log
            log.error("frame %d failed: %r", index, error, exc_info=error)

    def _check_pair(self, frame: Any) -> None:
        """Once per opened camera: are its (rectified) rows aligned? A misaligned pair gives confident
        nonsense, so say so in the log, with how to fix it (`branchrange.core.pair_check`)."""
        self._pair_checked = True
        left, right = frame.left, frame.right
        rectifier = getattr(self.pipeline, "rectifier", None)
        try:
            validate_pair(left, right)
            if rectifier is not None:
                left, right = rectifier.rectify(left, right)
            check_rectification(left, right).log(log)
        except ValueError as error:  # a frame the pipeline will reject anyway, with its own message
            log.debug("pair check skipped: %s", error)

    def _stereo(self, frame: Any, captured_at: float) -> None:
        """The stereo half of one frame, handed to the geometry worker."""
        if not self._pair_checked:
            self._check_pair(frame)
        started = time.monotonic()
        try:
            stage = stereo_stage(self.pipeline, frame, self.shedder.level)
        except Exception as error:  # noqa: BLE001 — one bad frame must not stop the vehicle's sensor
            self._reject(frame.index, error)
            return
        self._slot.put(_StereoOutput(stage, captured_at, started, time.monotonic()))

    def _start_workers(self) -> None:
        """With `stereo.workers` > 1: the worker processes, started and their pipelines built (once per run)."""
        if self.workers < 2 or (self._pool is not None and not self._pool.closed):
            return
        assert self._pipeline_factory is not None
        self._pool = StereoWorkers(self.workers, self._pipeline_factory, self._from_worker)
        self._warmed = False
        self._pool.wait_ready(self._stop)
        log.info("stereo stage in %d worker processes", self.workers)

    def warm_up(self, frame: Any) -> None:
        """Before `run`: start the stereo workers and run `frame` (a `StereoFrame`) once in each, as a caller
        warms its own pipeline, so that what a pipeline builds on its first frame is not timed; else the
        first frame of the run does it. Nothing to do with one worker (the caller's pipeline is the one used)."""
        self._start_workers()
        if self._pool is not None:
            self._pool.warm(frame, self._stop)
            self._warmed = True

    def stereo_worker_pids(self) -> list[int]:
        """The stereo worker processes' ids (`stereo.workers` > 1, once started), else none: for a caller
        that accounts for their CPU time."""
        return [] if self._pool is None or self._pool.closed else self._pool.pids()

    def _dispatch(self, frame: Any, captured_at: float) -> None:
        """The stereo half of one frame, handed to a worker process (`stereo.workers` > 1)."""
        if not self._pair_checked:
            self._check_pair(frame)
        assert self._pool is not None
        if not self._warmed:
            self._warmed = True
            self._pool.warm(frame, self._stop)
        self._pool.submit(frame, captured_at, self.shedder.level)

    def _from_worker(self, output: WorkerOutput) -> None:
        """A worker's output, in capture order: on to the geometry thread, or rejected, or counted as lost."""
        if output.lost:
            self._count_error("stereo_worker_lost")
        elif output.error is not None:
            self._reject(output.index, output.error)
        else:
            self._slot.put(_StereoOutput(output.stage, output.captured_at, output.started_at, output.halfway_at, True))

    def _wait_idle(self) -> None:
        """Until every frame taken so far has been published (or rejected, or lost)."""
        if self._pool is not None:
            self._pool.wait_idle()
        self._slot.wait_idle()

    def _geometry_worker(self) -> None:
        """The geometry + send thread: the newest stereo output → result → relay, log, /latest, observers."""
        while (item := self._slot.take()) is not None:
            try:
                finish = self.pipeline.finish_frame if item.cut_points_done else self.pipeline.geometry_stage
                self._publish(finish(item.stage), item)
            except Exception as error:  # noqa: BLE001 — the next frame may well be fine
                self._reject(item.stage.index, error)
            finally:
                self._slot.task_done()

    def _publish(self, result: FrameResult, item: _StereoOutput) -> None:
        now = time.monotonic()
        age = now - item.captured_at
        result = replace(
            result,
            latency=Latency(
                round(1000 * (item.stereo_started_at - item.captured_at), 3),
                round(1000 * (item.stereo_done_at - item.captured_at), 3),
                round(1000 * age, 3),
            ),
        )
        if self.relay is not None:
            self.relay.publish(result, captured_at=item.captured_at)
            result = replace(result, targets=self.relay.targets())  # fused in local NED, for the log and /latest
        self._check_age(age)
        self._shed(age)
        self._note_light(result)
        if self._results is not None:
            if self._reopened is not None:  # indices and timestamps start again from the new source's: say why
                self._results.write(camera_reopened_line(*self._reopened, first=result))
                self._reopened = None
            self._results.write(result_line(result))
        self._latest = (result, item.captured_at)
        for observer in self.observers:
            try:
                observer(result, self.pipeline.last)
            except Exception as error:  # noqa: BLE001 — a viewer must never stop the daemon
                log.warning("result observer %r failed: %r", observer, error)
        with self._counts_lock:
            self.frames += 1
            self._latencies.append(age)
        if self.metrics is not None:
            self.metrics.observe_frame(age, "daemon")
        if len(self._warmup) < WARMUP_FRAMES:
            self._warmup.append((age, item.stereo_done_at - item.stereo_started_at, now - item.stereo_done_at))
            if len(self._warmup) == WARMUP_FRAMES:
                self._report_speed()

    def _report_speed(self) -> None:
        """Once, after the first frames: can this configuration meet `max_result_age_s`, and if not, what to change."""
        if self._speed_reported or not self._warmup:
            return
        self._speed_reported = True
        age, stereo, geometry = (statistics.median(column) for column in zip(*self._warmup))
        limit = self.cfg.mavlink.max_result_age_s
        if age <= limit:
            log.info(
                "speed: capture → publish %.0f ms (stereo %.0f ms, geometry %.0f ms) within "
                "mavlink.max_result_age_s = %.0f ms",
                1000 * age,
                1000 * stereo,
                1000 * geometry,
                1000 * limit,
            )
            return
        self._speed_warned = True
        advice = (
            "set stereo.mode = 'roi'"
            if self.cfg.stereo.mode != "roi"
            else "lower stereo.max_disp to the working range, or roi.coarse_width"
        )
        if self.cfg.stereo.backend != "sgbm":
            advice += ", or use stereo.backend = 'sgbm' on this computer"
        log.warning(
            "speed: capture → publish takes %.0f ms (stereo %.0f ms, geometry %.0f ms), more than "
            "mavlink.max_result_age_s = %.0f ms: every result goes out as 'no target'. To fix: %s",
            1000 * age,
            1000 * stereo,
            1000 * geometry,
            1000 * limit,
            advice,
        )

    def _note_light(self, result: FrameResult) -> None:
        """Log when the measured light changes class (`branchrange.core.light_check`): out of normal light the
        confidences are read through another calibration, and in dark or noisy light no target is given."""
        light = result.masks.light
        if light is None or light.light == self._light:
            return
        self._light = light.light
        (log.info if light.light == "normal" else log.warning)("frame %d: %s", result.frame.index, light.message)

    def _check_age(self, age_s: float) -> None:
        """Count a result that was stale on publishing; after a warm-up that was fast enough, warn on the
        first one (during the warm-up, the speed report says it)."""
        if age_s <= self.cfg.mavlink.max_result_age_s:
            return
        self.late += 1
        if len(self._warmup) >= WARMUP_FRAMES and not self._speed_warned:
            self._speed_warned = True
            log.warning(
                "frame took %.0f ms, more than mavlink.max_result_age_s = %.0f ms: its result goes out as "
                "'no target' (the computer may be busy with something else)",
                1000 * age_s,
                1000 * self.cfg.mavlink.max_result_age_s,
            )

    def _shed(self, age_s: float) -> None:
        """Take the work level this result's age asks for (`load_shedding`), and say so when it changes."""
        change = self.shedder.observe(age_s)
        if change is None:
            return
        limit_ms = 1000 * self.cfg.mavlink.max_result_age_s
        if change.raised:
            log.warning(
                "load shedding: level %d (%s): capture → publish %.0f ms is near mavlink.max_result_age_s = %.0f ms",
                change.level,
                self.shedder.actions,
                1000 * change.age_s,
                limit_ms,
            )
        else:
            log.info(
                "load shedding: back to level %d (%s): capture → publish %.0f ms, well within %.0f ms",
                change.level,
                self.shedder.actions,
                1000 * change.age_s,
                limit_ms,
            )

    def _status(self, since: float, now: float, frames_then: int) -> None:
        with self._counts_lock:
            fps = (self.frames - frames_then) / max(now - since, 1e-9)
            latency = 1000 * sum(self._latencies) / len(self._latencies) if self._latencies else 0.0
            self._latencies.clear()
        state = None if self.relay is None else self.relay.link_state()
        link = "off" if state is None else ("up" if state["connected"] else "down")
        pose = "off" if state is None else state["mode"]  # world: fused in local NED; camera: no vehicle state
        log.info(
            "status frames=%d fps=%.1f latency_ms=%.0f dropped=%d dropped_late=%d skipped=%d corrupt=%d late=%d "
            "camera=%s link=%s pose=%s shed=%d",
            self.frames,
            fps,
            latency,
            self.dropped,
            self.dropped_late,
            self.skipped,
            self.corrupt,
            self.late,
            "lost" if self.camera_lost else "ok",
            link,
            pose,
            self.shedder.level,
        )

    def _done(self, max_frames: int | None) -> bool:
        return self._stop.is_set() or (max_frames is not None and self.frames >= max_frames)

    def run(self, max_frames: int | None = None) -> int:
        """Process frames until the source ends, `max_frames` are done or `stop()`; returns frames done."""
        worker = threading.Thread(target=self._geometry_worker, name="geometry-send", daemon=True)
        self._slot = NewestSlot()
        worker.start()
        self._start_workers()
        timeout = self.cfg.camera.stall_timeout_s
        source = self._try_open()
        stalls = 0
        status_at, frames_then = time.monotonic(), self.frames
        # the stall clock runs from the newest frame's arrival, not from when this thread is free to wait:
        # a frame in processing (up to a second on a loaded CPU) must not delay "camera lost"
        newest_at = status_at
        try:
            while not self._done(max_frames):
                now = time.monotonic()
                if now - status_at >= self.cfg.log.status_interval_s:
                    self._status(status_at, now, frames_then)
                    status_at, frames_then = now, self.frames
                stamped = None
                if source is None:  # not opened: again every stall timeout, so it is back within one
                    self._set_camera_lost(True)
                    if not self._stop.wait(timeout):
                        source, stalls = self._try_open(quiet=True), 0
                    newest_at = time.monotonic()
                    continue
                else:
                    if self._pool is not None:  # the newest frame once a worker can take it, not before
                        self._pool.wait_free(self._stop)
                    try:
                        wait = max(STALL_GRACE_S, newest_at + timeout - time.monotonic())
                        stamped = source.get_stamped(timeout=wait)
                        newest_at = time.monotonic() if stamped is None else stamped[1]
                    except StopIteration:
                        log.info("source ended")
                        break
                    except CorruptFrameError as exc:
                        self._on_corrupt(exc)
                        continue
                    except SourceDisconnected as exc:
                        log.warning("camera disconnected: %s", exc)
                if stamped is None or source is None or source.is_lost:
                    self._set_camera_lost(True)
                    stalls += stamped is None
                    if stalls >= REOPEN_AFTER_STALLS:
                        source, stalls = self._reopen(source), 0
                    if stamped is None or source is None:  # (a frame only ever comes from an open source)
                        continue
                stalls = self._corrupt_in_a_row = 0
                self._set_camera_lost(False)
                if not self._is_newer(stamped[0]):
                    continue
                self._camera_dropped = self._dropped_by_closed_sources + source.dropped
                self.dropped_late = self._dropped_late_by_closed_sources + source.dropped_late
                if max_frames is not None:
                    self._wait_idle()  # a counted run processes every frame it takes, and no more
                    if self._done(max_frames):
                        break
                if self._pool is None:
                    self._stereo(stamped[0], capture_time(*stamped))
                else:
                    self._dispatch(stamped[0], capture_time(*stamped))
        finally:
            if source is not None:
                source.close()
            self._wait_idle()  # the last stereo outputs still get their geometry and send
            if self._pool is not None:
                self._pool.close()
            self._slot.close()
            worker.join()
        self._report_speed()  # a run shorter than the warm-up
        self._status(status_at, time.monotonic(), frames_then)
        return self.frames

    def _is_newer(self, frame: Any) -> bool:
        """Whether `frame` was captured after the newest frame of this camera so far; counts and logs (once
        per opened camera) a frame that was not: a repeated image or one out of order."""
        newest = self._newest_capture_ns
        if newest is None or frame.timestamp_ns > newest:
            self._newest_capture_ns = frame.timestamp_ns
            return True
        self.repeated += 1
        self._count_error("repeated_frame")
        if self._repeat_logged_for != self.reopens:
            self._repeat_logged_for = self.reopens
            log.warning(
                "frame %d captured no later than the frame before it (a repeated image or frames out of order): "
                "skipped, as are the next such frames",
                frame.index,
            )
        return False

    def _on_corrupt(self, error: CorruptFrameError) -> None:
        """Skip an unreadable frame; several in a row mean the camera (or the recording) is gone."""
        self.corrupt += 1
        self._corrupt_in_a_row += 1
        self._count_error("corrupt_frame")
        log.warning("corrupt frame skipped: %s", error)
        if self._corrupt_in_a_row == CORRUPT_FRAMES_LOST:
            log.warning("%d unreadable frames in a row: treating the camera as lost", CORRUPT_FRAMES_LOST)
            self._set_camera_lost(True)

    def _try_open(self, quiet: bool = False) -> LatestFrameSource | None:
        """A fresh source with its capture thread, or None (logged; `quiet`: the retries of an outage already
        logged, at debug level) when the camera cannot be opened."""
        try:
            return LatestFrameSource(self._open_source())
        except SourceError as exc:
            (log.debug if quiet else log.error)("cannot open the camera: %s", exc)
            return None

    def _reopen(self, source: LatestFrameSource | None) -> LatestFrameSource | None:
        """Close a stalled source and open a fresh one; tracked branches are forgotten, and the results log
        gets a camera-reopened marker before the next result."""
        reason = f"no frame for {REOPEN_AFTER_STALLS} stall timeouts of {self.cfg.camera.stall_timeout_s:g} s"
        log.warning("%s: reopening the camera", reason)
        if source is not None:
            source.close()
            self._dropped_by_closed_sources += source.dropped
            self._dropped_late_by_closed_sources += source.dropped_late
        self.reopens += 1
        self._pair_checked = False  # a camera plugged in again may be another one
        self._wait_idle()  # the tracker (and the log's order) is the geometry thread's until then
        self._reopened = (reason, self.reopens, utc_now())
        self._newest_capture_ns = None  # a new source's timestamps may start again lower
        self.pipeline.reset()
        return self._try_open()

    def close(self) -> None:
        """Close the results log and the relay (the source is closed by `run`)."""
        if self.relay is not None:
            self.relay.close()
        if self._results is not None:
            self._results.close()
            self._results = None
