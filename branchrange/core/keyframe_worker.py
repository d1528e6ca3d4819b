"""The segmenter off the stereo thread: keyframes computed in their own worker, while the frames go on.

With `[roi] keyframe_worker = true` the roi mode's keyframe — the coarse pass, the segmenter's look and its
full-resolution instances, ~150–250 ms a frame at HD720 on 2 CPU cores — runs on this worker's own thread.
The stereo thread hands it a frame (`submit`, never blocking: a busy worker is not given another) and goes
on tracking the branches it has; when the keyframe is done (`take`), its instances are for a frame some
100–300 ms old, and the stereo thread carries them to its newest frame by the same propagation as any
tracked frame (`branch_propagation`, its search started at the image's global motion since then,
`global_shift`). The worker has its own stereo matchers (an OpenCV matcher object is not safe to run from
two threads) and is the segmenter's only user while it works.

Why a thread and not a process: OpenCV and onnxruntime/torch release the GIL while they compute, and the
hand-over of an HD720 pair and its label image to a process costs more than the GIL does here
(`benchmarks/keyframe_handover.py`).

A keyframe that raises ends the worker's thread, as a crash would: the failure is logged, the frame's
keyframe is lost (tracks go on ageing until `roi.track_max_age_s` drops them: results go stale, never
wrong), and the next `submit` starts a new thread (counted in `restarts`).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from branchrange.core.masks import BranchMasks

log = logging.getLogger(__name__)

#: The global image motion between a keyframe and the frame it is carried to is found on the whole grey frame
#: brought down to about this width (phase correlation: ~1 ms at HD720 / 4).
GLOBAL_SHIFT_WIDTH = 320


@dataclass(frozen=True, eq=False)
class Keyframe:
    """A keyframe's outcome: its rectified left image in grey (`uint8 H×W`), its instances (full resolution,
    None when the frame had no valid disparity to segment), each branch's disparity range (id → [low, high)
    px, `roi.branch_gates`), and its capture time (ns)."""

    grey: np.ndarray
    masks: BranchMasks | None
    gates: dict[int, tuple[float, float]]
    timestamp_ns: int


#: What the worker runs: (rectified left `uint8 H×W×3`, rectified right, capture time ns) → its `Keyframe`.
KeyframeJob = Callable[[np.ndarray, np.ndarray, int], Keyframe]


class KeyframeWorker:
    """One keyframe at a time on a thread of its own; see the module docstring."""

    def __init__(self, job: KeyframeJob) -> None:
        self._job = job
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._pending: tuple[np.ndarray, np.ndarray, int, int] | None = None  # (left, right, ns, generation)
        self._running = False
        self._done: Keyframe | None = None
        self._generation = 0  # bumped by `forget`: a keyframe of an older sequence is never taken
        self._thread: threading.Thread | None = None
        self._closed = False
        self._crashed = False  # the thread's keyframe raised: that thread is ending, the next `submit` starts another
        self.restarts = 0
        self.failures = 0
        self.last_error: str | None = None

    @property
    def busy(self) -> bool:
        """A keyframe is queued or being computed."""
        with self._lock:
            return self._pending is not None or self._running

    def submit(self, left: np.ndarray, right: np.ndarray, timestamp_ns: int) -> bool:
        """Hand the worker a frame (rectified `uint8 H×W×3` pair, capture time ns); False, and nothing done,
        when it is busy. Starts (or, after a crash, restarts) its thread."""
        with self._lock:
            if self._closed or self._pending is not None or self._running:
                return False
            self._pending = (left, right, int(timestamp_ns), self._generation)
            self._ensure_thread()
            self._wake.notify()
            return True

    def take(self, wait_s: float = 0.0) -> Keyframe | None:
        """The finished keyframe (once), waiting up to `wait_s` (s) for one in flight; None when there is none."""
        with self._wake:
            if self._done is None and wait_s > 0 and (self._pending is not None or self._running):
                self._wake.wait_for(
                    lambda: self._done is not None or (self._pending is None and not self._running), wait_s
                )
            done, self._done = self._done, None
            return done

    def forget(self) -> None:
        """Drop what is queued or finished (a new sequence): a keyframe in flight is thrown away when done."""
        with self._lock:
            self._generation += 1
            self._pending = None
            self._done = None

    def close(self) -> None:
        """Stop the thread (after the keyframe in flight, if any)."""
        with self._wake:
            self._closed = True
            self._pending = None
            self._wake.notify_all()
        thread = self._thread
        if thread is not None:
            thread.join(timeout=5.0)

    def _ensure_thread(self) -> None:
        """Start the thread, or a new one when the last ended on a failure (called with the lock held)."""
        if self._thread is not None and self._thread.is_alive() and not self._crashed:
            return
        if self._thread is not None:
            self._crashed = False
            self.restarts += 1
            log.warning("keyframe worker restarted (restart %d) after: %s", self.restarts, self.last_error)
        self._thread = threading.Thread(target=self._run, name="keyframe-worker", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            with self._wake:
                self._wake.wait_for(lambda: self._pending is not None or self._closed)
                if self._closed:
                    return
                assert self._pending is not None
                left, right, timestamp_ns, generation = self._pending
                self._pending, self._running = None, True
            try:
                keyframe = self._job(left, right, timestamp_ns)
            except Exception as error:  # a crash of the keyframe: logged, and this thread ends like a crashed one
                with self._wake:
                    self._running = False
                    self._crashed = True
                    self.failures += 1
                    self.last_error = f"{type(error).__name__}: {error}"
                    self._wake.notify_all()
                log.error(
                    "keyframe worker failed on the frame captured at %d ns (%s): tracks age until it is restarted",
                    timestamp_ns,
                    self.last_error,
                )
                return
            with self._wake:
                self._running = False
                if generation == self._generation:
                    self._done = keyframe
                self._wake.notify_all()


def global_shift(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """(du, dv) px the whole image moved from the `uint8 H×W` grey `before` to `after`: phase correlation at
    less resolution (a keyframe's instances are 100–300 ms old when they arrive;
    at 20°/s of yaw the view has moved ~70 px, more than a track's search), on frames about
    `GLOBAL_SHIFT_WIDTH` px wide."""
    factor = max(1, before.shape[1] // GLOBAL_SHIFT_WIDTH)
    size = (before.shape[1] // factor, before.shape[0] // factor)
    a = cv2.resize(before, size, interpolation=cv2.INTER_AREA).astype(np.float32)
    b = cv2.resize(after, size, interpolation=cv2.INTER_AREA).astype(np.float32)
    window = cv2.createHanningWindow(size, cv2.CV_32F)
    (du, dv), _ = cv2.phaseCorrelate(a, b, window)
    return float(du) * factor, float(dv) * factor
