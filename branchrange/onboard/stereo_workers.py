"""The stereo stage and the cut points in worker processes: each takes the next frame while the others work.

On a small CPU the daemon's stereo thread is bound by its own Python work (the interpreter lock):
more cores do not make one thread faster. Here `count` processes, each with its own pipeline built
by `pipeline_factory` (picklable: it is called in the new process), run `Pipeline.stereo_stage` and
then `Pipeline.cut_point_stage` (the geometry half's per-frame work: masks, the branches' disparity,
the trunk, the cut points) on one frame each; frames and outputs travel through shared memory
(`shm_transport`), the pipe carries only their small rest. Outputs are handed on (`on_output`) in
**capture order**: a frame finished early waits for the frames dispatched before it, so
`Pipeline.finish_frame` in the daemon, which keeps the tracker's state across frames, sees them as a
single thread would. The daemon's own process is then left with the capture, the frame's end and the
sending: the cores go to the workers.

What a worker needs from earlier frames: nothing, as long as `roi.keyframe_interval_s = 0` (the
segmenter on every frame; the default): the stereo stage then carries no state from one frame to the
next (the coarse-to-fine matchers and the segmenter are rebuilt identically in each process), and
the work level (`load_shedding`) goes with each frame. Keyframes carry instances from one frame to
the next, so the daemon runs them in its own thread (`Daemon`, one worker).

A worker that dies (killed, out of memory, a crash in native code) is started again and logged; the
frame it had is handed on as lost (`WorkerOutput.lost`), which the daemon counts as dropped.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import signal
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any

from branchrange.core.frame_results import stereo_stage
from branchrange.onboard.shm_transport import ShmReader, ShmWriter

log = logging.getLogger("branchrange.daemon")
#: How long (s) a closing pool waits for a worker to finish its frame and exit before terminating it.
CLOSE_TIMEOUT_S = 5.0
#: The sequence number of a warm-up frame (`StereoWorkers.warm`): its output is dropped.
WARM_UP = -1
#: The pause (s) before starting again a worker that died before it was ready (its pipeline could not be built).
RESTART_PAUSE_S = 1.0
#: How often (s) the collector thread wakes without news, to notice a pool being closed.
POLL_S = 0.1


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity, e.g. under `taskset`), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # no affinity on this OS
        return max(1, os.cpu_count() or 1)


def worker_count(configured: int) -> int:
    """`stereo.workers` as a number of processes: 0 is one per usable core."""
    return usable_cores() if configured == 0 else configured


@dataclass(frozen=True, eq=False)
class WorkerOutput:
    """One dispatched frame, back from its worker: its `CutPointStage` (`stage`), or the `error` the pipeline
    raised, or neither when the worker died with it (`lost`). `captured_at`, `started_at` (the stereo half),
    `halfway_at` (the cut points), `done_at`: monotonic s (a system-wide clock on Linux, so the worker's stamps
    compare with the daemon's)."""

    seq: int
    index: int
    captured_at: float
    started_at: float
    halfway_at: float
    done_at: float
    stage: Any = None
    error: Exception | None = None
    lost: bool = False


@dataclass
class _Worker:
    """One process, the pipe to it, the shared-memory ends for its frames, and the frame it has (seq)."""

    slot: int
    process: Any
    conn: Connection
    writer: ShmWriter
    reader: ShmReader
    ready: bool = False
    busy: tuple[int, int, float, float] | None = None  # (seq, frame index, captured_at, dispatched_at)


class StereoWorkers:
    """A pool of `count` stereo-stage processes; outputs go to `on_output` in the order frames were submitted.

    `submit` hands a frame to a free worker (`wait_free` first); a collector thread reads the answers,
    restarts dead workers and releases outputs in order. `restarts` and `lost` count dead workers and the
    frames they took with them.
    """

    def __init__(
        self, count: int, pipeline_factory: Callable[[], Any], on_output: Callable[[WorkerOutput], None]
    ) -> None:
        if count < 2:
            raise ValueError(f"a stereo worker pool needs at least 2 workers, got {count}")
        self.count = count
        self._factory = pipeline_factory
        self._on_output = on_output
        self._context = multiprocessing.get_context("spawn")  # no fork of a process running threads
        self._condition = threading.Condition()
        self._workers = [self._start(slot) for slot in range(count)]
        self._next_seq = 0  # the next frame submitted
        self._release_seq = 0  # the next frame handed on
        self._done: dict[int, WorkerOutput] = {}
        self._closing = False
        self.restarts = 0
        self.lost = 0
        self._collector = threading.Thread(target=self._collect, name="stereo-workers", daemon=True)
        self._collector.start()

    @property
    def closed(self) -> bool:
        """Whether `close` was called (the workers are gone)."""
        return self._closing

    def pids(self) -> list[int]:
        """The workers' process ids (for tests and diagnosis)."""
        with self._condition:
            return [worker.process.pid for worker in self._workers]

    def busy_pids(self) -> list[int]:
        """The process ids of the workers that have a frame now (not counting the warm-up frame)."""
        with self._condition:
            return [w.process.pid for w in self._workers if w.busy is not None and w.busy[0] != WARM_UP]

    def _start(self, slot: int) -> _Worker:
        ours, theirs = self._context.Pipe()
        process = self._context.Process(
            target=_serve,
            args=(theirs, self._factory, max(1, usable_cores() // self.count)),
            name=f"stereo-worker-{slot}",
            daemon=True,
        )
        process.start()
        theirs.close()
        return _Worker(slot, process, ours, ShmWriter(), ShmReader())

    def _free(self) -> _Worker | None:
        return next((w for w in self._workers if w.ready and w.busy is None), None)

    def wait_ready(self, stop: threading.Event) -> None:
        """Block until every worker has built its pipeline (or `stop` is set): the first frames are not
        dropped waiting for models to load."""
        with self._condition:
            while not all(w.ready for w in self._workers) and not stop.is_set() and not self._closing:
                self._condition.wait(POLL_S)

    def wait_free(self, stop: threading.Event) -> None:
        """Block until a worker is free for the next frame (or `stop` is set)."""
        with self._condition:
            while self._free() is None and not stop.is_set() and not self._closing:
                self._condition.wait(POLL_S)

    def warm(self, frame: Any, stop: threading.Event) -> None:
        """Run `frame` once in every worker and drop the outputs: what a pipeline builds on its first frame (the
        matchers, the model's first inference) is then built before the first frame that counts."""
        with self._condition:
            for worker in self._workers:
                if worker.ready and worker.busy is None:
                    worker.busy = (WARM_UP, int(frame.index), 0.0, time.monotonic())
                    try:
                        worker.conn.send((WARM_UP, worker.writer.pack(frame), 0))
                    except (BrokenPipeError, EOFError, OSError):  # the collector starts it again
                        pass
            while any(w.busy is not None for w in self._workers) and not stop.is_set() and not self._closing:
                self._condition.wait(POLL_S)

    def submit(self, frame: Any, captured_at: float, shed_level: int) -> None:
        """Hand `frame` (a `camera.sources.StereoFrame`) to a free worker, waiting for one."""
        with self._condition:
            self._condition.wait_for(lambda: self._free() is not None or self._closing)
            worker = self._free()
            if worker is None:  # closing
                return
            seq, self._next_seq = self._next_seq, self._next_seq + 1
            worker.busy = (seq, int(frame.index), captured_at, time.monotonic())
            try:
                worker.conn.send((seq, worker.writer.pack(frame), shed_level))
            except (BrokenPipeError, EOFError, OSError):  # it died just now: the collector hands the frame on as lost
                pass

    def wait_idle(self) -> None:
        """Block until every submitted frame has been handed on."""
        with self._condition:
            self._condition.wait_for(lambda: self._release_seq == self._next_seq or self._closing)

    def _collect(self) -> None:
        """The collector thread: answers in, dead workers restarted, outputs released in submission order."""
        while True:
            with self._condition:
                if self._closing:
                    return
                waitables = {w.conn: w for w in self._workers} | {w.process.sentinel: w for w in self._workers}
            for ready in wait(list(waitables), timeout=POLL_S):
                worker = waitables[ready]
                if self._workers[worker.slot] is not worker:  # its pipe and its end both ready: restarted already
                    continue
                if ready is worker.conn:
                    self._receive(worker)
                elif not worker.conn.poll():  # dead, with no answer left to read
                    self._restart(worker)

    def _receive(self, worker: _Worker) -> None:
        try:
            message = worker.conn.recv()
        except (EOFError, OSError):
            self._restart(worker)
            return
        if message == "ready":
            with self._condition:
                worker.ready = True
                self._condition.notify_all()
            return
        kind, seq, payload, started_at, halfway_at, done_at = message
        assert worker.busy is not None and worker.busy[0] == seq, "a worker answers the frame it was given"
        stamps = (seq, worker.busy[1], worker.busy[2], started_at, halfway_at, done_at)
        if kind == "ok":
            output = WorkerOutput(*stamps, stage=worker.reader.unpack(payload))
        else:
            output = WorkerOutput(*stamps, error=payload)
        self._finish(worker, output)

    def _restart(self, worker: _Worker) -> None:
        """A dead worker: log it, hand its frame on as lost, start a fresh process in its place."""
        if self._closing:
            return
        worker.process.join(timeout=1.0)
        if not worker.ready:  # it died building its pipeline: do not start one after the other in a tight loop
            time.sleep(RESTART_PAUSE_S)
        code = worker.process.exitcode
        busy = worker.busy
        log.warning(
            "stereo worker %d (pid %s) died (exit code %s)%s: started again",
            worker.slot,
            worker.process.pid,
            code,
            "" if busy is None else f" with frame {busy[1]}, which counts as dropped",
        )
        worker.conn.close()
        worker.reader.close(unlink=True)  # its output block: nobody else frees it now
        fresh = self._start(worker.slot)
        fresh.writer, fresh.reader = worker.writer, ShmReader()  # our frame block is ours: keep it
        with self._condition:
            self._workers[worker.slot] = fresh
            self.restarts += 1
        if busy is not None and busy[0] != WARM_UP:
            seq, index, captured_at, dispatched_at = busy
            with self._condition:
                self.lost += 1
            now = time.monotonic()
            self._finish(fresh, WorkerOutput(seq, index, captured_at, dispatched_at, now, now, lost=True))

    def _finish(self, worker: _Worker, output: WorkerOutput) -> None:
        """Note `output`, free its worker, and hand on every output whose predecessors are all in."""
        with self._condition:
            if worker.busy is not None and worker.busy[0] == output.seq:
                worker.busy = None
            if output.seq == WARM_UP:
                self._condition.notify_all()
                return
            self._done[output.seq] = output
            ready = []
            while self._release_seq in self._done:
                ready.append(self._done.pop(self._release_seq))
                self._release_seq += 1
        for item in ready:  # outside the lock: the geometry hand-over may wait
            self._on_output(item)
        with self._condition:
            self._condition.notify_all()

    def close(self) -> None:
        """Stop the workers (each finishes its frame first, up to `CLOSE_TIMEOUT_S`) and free their memory."""
        with self._condition:
            self._closing = True
            self._condition.notify_all()
        self._collector.join()
        for worker in self._workers:
            try:
                worker.conn.send(None)
            except (BrokenPipeError, OSError):
                pass
        for worker in self._workers:
            worker.process.join(timeout=CLOSE_TIMEOUT_S)
            if worker.process.is_alive():
                worker.process.terminate()
                worker.process.join()
            worker.conn.close()
            worker.writer.close()
            worker.reader.close(unlink=worker.process.exitcode != 0)


def _serve(conn: Connection, pipeline_factory: Callable[[], Any], cv_threads: int) -> None:
    """A worker process: build the pipeline, then the stereo stage and the cut points of each frame it gets until
    told to stop.
    `cv_threads`: OpenCV's threads here, the usable cores shared among the workers (OpenCV would otherwise
    start one per core in every worker, and the workers' threads would fight for the same cores)."""
    import cv2

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the daemon stops its workers
    cv2.setNumThreads(cv_threads)
    pipeline = pipeline_factory()
    reader, writer = ShmReader(), ShmWriter()
    conn.send("ready")
    try:
        while (message := conn.recv()) is not None:
            seq, packed, shed_level = message
            frame = reader.unpack(packed)
            started = halfway = time.monotonic()
            try:
                stage = stereo_stage(pipeline, frame, shed_level)
                halfway = time.monotonic()
                cut_stage = pipeline.cut_point_stage(stage)
            except Exception as error:  # noqa: BLE001 — the daemon decides (rejects the frame, logs a bug)
                conn.send(("error", seq, _sendable(error), started, halfway, time.monotonic()))
                continue
            conn.send(("ok", seq, writer.pack(cut_stage), started, halfway, time.monotonic()))
    except EOFError:  # the daemon is gone
        pass
    finally:
        writer.close()
        reader.close()


def _sendable(error: Exception) -> Exception:
    """`error` as it can cross the pipe: itself for bad input (a `ValueError` the daemon logs as a rejection),
    else a `RuntimeError` carrying the worker's traceback (an exception's own traceback does not pickle)."""
    if isinstance(error, ValueError):
        try:
            pickle.dumps(error)
            return error
        except Exception:  # noqa: BLE001 — an exception class that does not pickle
            return ValueError(str(error))
    return RuntimeError("in a stereo worker:\n" + "".join(traceback.format_exception(error)))
