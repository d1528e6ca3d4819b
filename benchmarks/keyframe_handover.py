"""Is a process worth it for the keyframe worker on 2 cores? The GIL's cost against the hand-over's.

Issue 36 item 2 asks to run a CPU-bound half in its own process where the GIL costs time, and to measure
what the hand-over costs. This script measures both on a rendered HD720 flight with the shipped
onboard settings (`--config`, default deploy/onboard_cpu.toml, keyframes on):

1. **the GIL's cost** — the stereo thread's tracked frame (`Pipeline.process` of a frame carried from a
   keyframe: propagation, region stereo, refinement, cut points), timed alone, then while the keyframe job
   (coarse pass + segmenter + full-resolution instances) runs without pause in a *thread* of the same process,
   then while it runs in a separate *process*. Both loads take a core's worth of CPU; only the thread shares
   the GIL. (thread − process) is what a process would win.
2. **the hand-over's cost** — one keyframe's round trip to a process: the rectified HD720 pair written into
   shared memory (`multiprocessing.shared_memory`), a message to the process, the label image (`int32 H×W`)
   written back and read, with an empty job; against the same round trip to a thread (a queue).

Prints a table and the CPU; `--json FILE` writes it. Timings on a shared machine: read them by the load
printed with them, and by the ratios within the run.

    .venv/bin/python benchmarks/keyframe_handover.py --sequence out/bench/approach/1280x720_v0.3_seed1
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import queue
import statistics
import threading
import time
from multiprocessing import shared_memory
from pathlib import Path
from typing import Any

import numpy as np
from machine import cpu_description, cpu_name  # a script's own folder is on its import path

ROOT = Path(__file__).resolve().parents[1]


def _pipeline(config_path: Path, sequence: Path, interval_s: float) -> tuple[Any, Any]:
    """The shipped pipeline (keyframes every `interval_s` s, on the stereo thread) and the flight's frames reader."""
    from branchrange.config.loader import load_config, parse_override, pipeline_for
    from camera.sources.replay import _DirectoryFrames

    frames = _DirectoryFrames(sequence, with_masks=False)
    overrides = [parse_override(f"roi.keyframe_interval_s={interval_s}"), parse_override("roi.keyframe_worker=false")]
    return pipeline_for(load_config(config_path, overrides), frames.calibration()), frames


def _frames(reader: Any, count: int) -> list[Any]:
    out = []
    for position in range(count):
        reader.seek(position)
        out.append(reader.read())
    return out


def _keyframe_loop(config_path: str, sequence: str, stop: Any, done: Any) -> None:
    """Keyframes without pause on the flight's first frames until `stop` is set (a thread's or a process's
    load); `done` counts them."""
    pipeline, reader = _pipeline(Path(config_path), Path(sequence), 10.0)
    frames = _frames(reader, 3)
    i = 0
    while not stop.is_set():
        frame = frames[i % len(frames)]
        pipeline.reset()
        pipeline.stereo_stage(frame.left, frame.right, None, frame.index, frame.timestamp_ns)
        with done.get_lock():
            done.value += 1
        i += 1


def tracked_frame_ms(pipeline: Any, frames: list[Any], rounds: int) -> list[float]:
    """Compute times (ms) of tracked frames: a keyframe on frame 0 (not timed), then frames 1.. carried from it."""
    times = []
    for _ in range(rounds):
        pipeline.reset()
        first = frames[0]
        pipeline.process(first.left, first.right, None, first.index, first.timestamp_ns)
        for frame in frames[1:]:
            start = time.perf_counter()
            result = pipeline.process(frame.left, frame.right, None, frame.index, frame.timestamp_ns)
            if result.origin == "tracked":
                times.append(1000 * (time.perf_counter() - start))
    return times


def _echo_process(names: tuple[str, str], shape: tuple[int, int, int], inbox: Any, outbox: Any) -> None:
    """The hand-over's far end: read the pair from shared memory, write a label image back, answer."""
    pair_memory, labels_memory = (shared_memory.SharedMemory(name=n) for n in names)
    pair = np.ndarray((2, *shape), np.uint8, buffer=pair_memory.buf)
    labels = np.ndarray(shape[:2], np.int32, buffer=labels_memory.buf)
    while (message := inbox.get()) is not None:
        labels[:] = pair[0, :, :, 0]  # touch the frame, as a segmenter reads it
        outbox.put(message)
    pair_memory.close()
    labels_memory.close()


def process_round_trip_ms(left: np.ndarray, right: np.ndarray, count: int) -> list[float]:
    """Round trips (ms) of a pair to a process through shared memory and a label image back."""
    pair_memory = shared_memory.SharedMemory(create=True, size=2 * left.nbytes)
    labels_memory = shared_memory.SharedMemory(create=True, size=left.shape[0] * left.shape[1] * 4)
    context = mp.get_context("spawn")
    inbox, outbox = context.Queue(), context.Queue()
    worker = context.Process(
        target=_echo_process, args=((pair_memory.name, labels_memory.name), left.shape, inbox, outbox)
    )
    worker.start()
    pair = np.ndarray((2, *left.shape), np.uint8, buffer=pair_memory.buf)
    labels = np.ndarray(left.shape[:2], np.int32, buffer=labels_memory.buf)
    times = []
    try:
        for i in range(count + 3):  # the first round trips start the process: not counted
            start = time.perf_counter()
            pair[0], pair[1] = left, right
            inbox.put(i)
            outbox.get(timeout=60)
            _ = labels.copy()  # the stereo thread keeps its own copy
            if i >= 3:
                times.append(1000 * (time.perf_counter() - start))
    finally:
        inbox.put(None)
        worker.join(timeout=10)
        pair_memory.close()
        pair_memory.unlink()
        labels_memory.close()
        labels_memory.unlink()
    return times


def thread_round_trip_ms(left: np.ndarray, right: np.ndarray, count: int) -> list[float]:
    """Round trips (ms) of a pair to a thread through a queue and a label image back."""
    inbox: queue.Queue[Any] = queue.Queue()
    outbox: queue.Queue[Any] = queue.Queue()

    def echo() -> None:
        while (message := inbox.get()) is not None:
            outbox.put(message[0][:, :, 0].astype(np.int32))

    worker = threading.Thread(target=echo, daemon=True)
    worker.start()
    times = []
    for _ in range(count):
        start = time.perf_counter()
        inbox.put((left, right))
        outbox.get(timeout=60)
        times.append(1000 * (time.perf_counter() - start))
    inbox.put(None)
    worker.join(timeout=10)
    return times


def p50(values: list[float]) -> float | None:
    return round(statistics.median(values), 1) if values else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequence", type=Path, required=True, help="a rendered HD720 flight recording")
    parser.add_argument("--config", type=Path, default=ROOT / "deploy" / "onboard_cpu.toml")
    parser.add_argument("--frames", type=int, default=5, help="frames per keyframe round (the first is the keyframe)")
    parser.add_argument("--rounds", type=int, default=6, help="rounds of tracked frames per load")
    parser.add_argument("--round-trips", type=int, default=50)
    parser.add_argument("--json", type=Path, help="write the report here")
    args = parser.parse_args(argv)

    pipeline, reader = _pipeline(args.config, args.sequence, 10.0)
    frames = _frames(reader, args.frames)
    tracked_frame_ms(pipeline, frames, 1)  # warm-up: the models and matchers are built
    report: dict[str, Any] = {"cpu": cpu_description(), "sequence": str(args.sequence), "config": str(args.config)}
    rows = {}
    for load in ("none", "thread", "process"):
        stop: Any
        done: Any
        runner: Any = None
        if load == "thread":
            stop, done = threading.Event(), mp.Value("i", 0)
            runner = threading.Thread(
                target=_keyframe_loop, args=(str(args.config), str(args.sequence), stop, done), daemon=True
            )
        elif load == "process":
            context = mp.get_context("spawn")
            stop, done = context.Event(), context.Value("i", 0)
            runner = context.Process(target=_keyframe_loop, args=(str(args.config), str(args.sequence), stop, done))
        if runner is not None:
            runner.start()
            while done.value < 1:  # the load has built its pipeline and runs
                time.sleep(0.2)
            counted = done.value
        began, load_average = time.perf_counter(), os.getloadavg()[0]
        times = tracked_frame_ms(pipeline, frames, args.rounds)
        seconds = time.perf_counter() - began
        keyframes_per_s = None
        if runner is not None:
            keyframes_per_s = round((done.value - counted) / seconds, 2)
            stop.set()
            runner.join(timeout=60)
        rows[load] = {
            "tracked_frame_ms_p50": p50(times),
            "tracked_frames": len(times),
            "load_keyframes_per_s": keyframes_per_s,
            "load_average_1min": round(load_average, 2),
        }
    left, right = frames[0].left, frames[0].right
    report["tracked_frame"] = rows
    report["round_trip_ms_p50"] = {
        "process_shared_memory": p50(process_round_trip_ms(left, right, args.round_trips)),
        "thread_queue": p50(thread_round_trip_ms(left, right, args.round_trips)),
    }
    print(f"keyframe worker: thread or process? {cpu_name()}; {args.sequence.name}, {args.config.name}")
    header = ("beside the stereo thread", "tracked frame p50 ms", "frames", "keyframes/s", "load")
    print(f"{header[0]:32s} {header[1]:>21s} {header[2]:>7s} {header[3]:>12s} {header[4]:>6s}")
    for load, row in rows.items():
        print(
            f"{load:32s} {row['tracked_frame_ms_p50']!s:>21s} {row['tracked_frames']:>7d} "
            f"{row['load_keyframes_per_s']!s:>12s} {row['load_average_1min']:>6.2f}"
        )
    trips = report["round_trip_ms_p50"]
    print(
        f"hand-over round trip p50 (HD720 pair in, int32 labels out): process + shared memory "
        f"{trips['process_shared_memory']} ms, thread + queue {trips['thread_queue']} ms"
    )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
