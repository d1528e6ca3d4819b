"""Recordings killed with SIGKILL at random instants: does each one replay up to its last complete frame?

Each trial forks a process that records numbered frames (320×240 noise, PNG, so a kill often lands
inside an image write) through `camera.sources.Recorder` and counts each `write()` that returned;
the parent kills it with SIGKILL after a random delay (seeded) and replays the directory with
`ReplaySource`. A trial passes when the replay gives the frames 0…n-1, each bit-for-bit as written,
where n is the count of returned writes or one more (a kill between a frame's row reaching
timestamps.csv and the counter's update); a recording killed before any frame's row must be refused
with a clear error (RecordingFormatError). The table counts trials, passes, how many frames were lost at the
end (rows dropped by the reader) and how many kills left a stray temporary file (a kill inside an
image write). The baseline is the same recorder run to completion, in frames per second.

    .venv/bin/python benchmarks/recording_kill.py --kills 100 --json out/recording_kill.json

`tests/test_recording_kill.py` runs 20 seeded kills through the same functions.
"""

from __future__ import annotations

import argparse
import collections
import json
import multiprocessing
import os
import random
import signal
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from multiprocessing.sharedctypes import Synchronized
from pathlib import Path

import numpy as np

from camera.sources import Recorder, ReplaySource, SourceUnavailable, StereoFrame

WIDTH, HEIGHT = 320, 240
PERIOD_NS = 33_333_333
#: Kills land uniformly in [0, this] seconds after the recording process starts (a few dozen frames).
DEFAULT_WINDOW_S = 0.6


def numbered_frame(index: int) -> StereoFrame:
    """Frame `index` of the test recording: noise seeded by the index (so each frame can be checked
    bit for bit), stamped 1 s + index × 33.3 ms."""
    rng = np.random.default_rng(index)
    left, right = (rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8) for _ in range(2))
    return StereoFrame(left, right, 1_000_000_000 + index * PERIOD_NS, index)


def _record_until_killed(directory: Path, returned_writes: Synchronized) -> None:
    """The recording process: numbered frames, forever, counting each `write()` that returned."""
    recorder = Recorder(directory)
    index = 0
    while True:
        recorder.write(numbered_frame(index))
        index += 1
        returned_writes.value = index


@dataclass(frozen=True)
class KillTrial:
    """One recording killed after `delay_s`: what the recorder confirmed, what replay gave back, and the verdict."""

    delay_s: float
    returned_writes: int
    replayed: int
    lost_at_end: int
    stray_temporary_files: int
    passed: bool
    detail: str


def _replayed_frames(directory: Path) -> tuple[int, int, str]:
    """(frames replayed, frames lost at the end, "" or why the replay is wrong) of a killed recording."""
    with ReplaySource(directory, pace="fast") as source:
        replayed = 0
        for frame in source:
            expected = numbered_frame(replayed)
            same = np.array_equal(frame.left, expected.left) and np.array_equal(frame.right, expected.right)
            if not same or (frame.index, frame.timestamp_ns) != (expected.index, expected.timestamp_ns):
                return replayed, source.frames_lost_at_end, f"frame {replayed} differs from the one written"
            replayed += 1
        return replayed, source.frames_lost_at_end, ""


def kill_while_recording(directory: Path, delay_s: float) -> KillTrial:
    """Record into `directory` (new) in a forked process, SIGKILL it after `delay_s` seconds and judge the replay."""
    context = multiprocessing.get_context("fork")  # no re-import: the kill lands while recording, not starting
    returned_writes = context.Value("i", 0)
    process = context.Process(target=_record_until_killed, args=(directory, returned_writes), daemon=True)
    process.start()
    time.sleep(delay_s)
    assert process.pid is not None
    os.kill(process.pid, signal.SIGKILL)
    process.join()
    confirmed = returned_writes.value
    stray = sum(1 for path in directory.rglob(".*.tmp"))
    try:
        replayed, lost, problem = _replayed_frames(directory)
    except SourceUnavailable as error:  # killed before the first row: refused (RecordingFormatError), with its reason
        return KillTrial(delay_s, confirmed, 0, 0, stray, confirmed == 0, f"refused: {error}")
    if not problem and not confirmed <= replayed <= confirmed + 1:
        problem = f"replayed {replayed} frames; {confirmed} writes had returned"
    return KillTrial(delay_s, confirmed, replayed, lost, stray, not problem, problem or "ok")


def kill_trials(root: Path, kills: int, seed: int, window_s: float = DEFAULT_WINDOW_S) -> list[KillTrial]:
    """`kills` trials in fresh folders under `root`, delays drawn uniformly from [0, window_s] with `seed`."""
    rng = random.Random(seed)
    return [kill_while_recording(root / f"kill_{i:03d}", rng.uniform(0.0, window_s)) for i in range(kills)]


def recording_fps(directory: Path, frames: int) -> float:
    """Frames per second of the same recorder run to completion (the baseline: what the kills interrupt)."""
    pairs = [numbered_frame(i) for i in range(frames)]
    start = time.perf_counter()
    with Recorder(directory) as recorder:
        for frame in pairs:
            recorder.write(frame)
    return frames / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=100, help="recordings to kill (default 100)")
    parser.add_argument("--seed", type=int, default=2026, help="seed of the kill instants")
    parser.add_argument("--window", type=float, default=DEFAULT_WINDOW_S, help="kills land in [0, WINDOW] s")
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args(argv)
    from machine import cpu_description, cpu_name  # a script's own folder is on its import path

    with tempfile.TemporaryDirectory(prefix="recording_kill_") as temporary:
        root = Path(temporary)
        fps = recording_fps(root / "baseline", 60)
        trials = kill_trials(root, args.kills, args.seed, args.window)
    passed = sum(t.passed for t in trials)
    lost = collections.Counter(t.lost_at_end for t in trials)
    confirmed = [t.returned_writes for t in trials]
    report = {
        "cpu": cpu_name(),
        "load_average_1min": cpu_description()["load_average_1min"],
        "kills": len(trials),
        "all_replayed_to_last_complete_frame": passed == len(trials),
        "passed": passed,
        "frames_lost_at_end": {str(k): v for k, v in sorted(lost.items())},
        "killed_before_first_frame": sum(t.replayed == 0 for t in trials),
        "killed_inside_an_image_write": sum(t.stray_temporary_files > 0 for t in trials),
        "frames_confirmed": {
            "min": min(confirmed),
            "median": sorted(confirmed)[len(confirmed) // 2],
            "max": max(confirmed),
        },
        "baseline_recording_fps": round(fps, 1),
        "failures": [asdict(t) for t in trials if not t.passed],
    }
    frames = report["frames_confirmed"]
    rows = [
        ("kills", report["kills"]),
        ("all replayed to their last complete frame", "yes" if passed == len(trials) else "NO"),
        ("passed", passed),
        *((f"frames lost at the end = {count}", n) for count, n in report["frames_lost_at_end"].items()),
        ("killed before the first frame", report["killed_before_first_frame"]),
        ("killed inside an image write (stray .tmp)", report["killed_inside_an_image_write"]),
        ("frames confirmed before the kill min/med/max", f"{frames['min']}/{frames['median']}/{frames['max']}"),
        ("baseline: recording to completion, frames/s", f"{fps:.1f}"),
    ]
    print(f"recording killed with SIGKILL at random instants ({report['cpu']}, load {report['load_average_1min']})")
    for label, value in rows:
        print(f"{label:<46} {value:>8}")
    for failure in report["failures"]:
        print(f"FAILED after {failure['delay_s']:.3f} s: {failure['detail']}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0 if report["all_replayed_to_last_complete_frame"] else 1


if __name__ == "__main__":
    sys.exit(main())
