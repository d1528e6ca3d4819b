"""Does a paced replay keep its schedule? `ReplaySource(pace="recorded")` against the pacing it replaced.

A recording of `--unique` HD720 frames (one synthetic tree scene, `stereo.synth`, shifted a few pixels
per frame, with its instance masks: PNG decoding as in a synthetic flight recording) is replayed in a
loop for `--frames` frames at its 15 fps, the way the daemon reads a camera: a `LatestFrameSource`
capture thread drains the source while the main thread stands for the pipeline, holding the CPU
(and Python's GIL, as the pipeline's Python stages do) for `--work-ms` per frame. `--load N` adds N
processes that spin on a core each (a busy companion computer). Each variant runs in the same
invocation, one after the other, under the same added load (on a shared machine, other users' load
still changes between them: compare within a run, and repeat a run before trusting a small gap):

- `decode-then-sleep` — the baseline: the old pacing, re-implemented here — decode the frame, then
  sleep until its slot; never drop a frame, so once late it stays late;
- `recorded` — `camera.sources.ReplaySource(pace="recorded")`: wait for the slot before decoding
  (starting early by the recent decode and wake-up times), drop and count the frames that would be
  released more than half a period (33 ms) late;
- `recorded-20ms` — the same with `max_late_ms=20`: the issue's 20 ms schedule target as the limit.

Reported per variant: frames released and dropped, the schedule error of released frames (release −
slot, slot = start + (t_i − t_0), milliseconds: p50, p95, max), frames released more than 20 ms late,
and the lag of the last frame. `--json FILE` writes the same, with the CPU (`machine.py`), the
1-minute load average at the start, and the settings; `ratio_to_baseline` gives the p95 and max
errors against the baseline of the same run.

    .venv/bin/python benchmarks/replay_pacing.py --frames 300 --load 1 --work-ms 40 --json out/replay_pacing.json

`replay_pacing_results.json` (that command) and `replay_pacing_results_no_extra_load.json` (`--work-ms 0
--load 0`) beside this script are runs on the shared 2-core development machine, loaded by others too.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from machine import cpu_description, cpu_name  # a script's own folder is on its import path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_RECORDING = ROOT / "out" / "bench" / "pacing_hd720"
PERIOD_NS = 66_666_667  # 15 fps, the ZED Mini's rate in the onboard configuration
LATE_MS = 20.0
#: ReplaySource's `max_late_ms` per variant (None: its default, half a period).
MAX_LATE_MS = {"recorded": None, "recorded-20ms": LATE_MS}


def write_recording(path: Path, unique: int) -> None:
    """`unique` HD720 frames of one synthetic tree scene, shifted 2 px a frame, 15 fps, with masks."""
    from camera.sources import Recorder, StereoFrame
    from stereo.synth import SynthCamera, render_scene

    print(f"rendering a {unique}-frame HD720 recording into {path} (once) ...", file=sys.stderr)
    camera = SynthCamera.zed_mini(1280, 720)
    scene = render_scene(0, camera)
    with Recorder(path, source_spec="benchmarks/replay_pacing") as recorder:
        for i in range(unique):
            shift = 2 * i
            recorder.write(
                StereoFrame(
                    np.roll(scene.left, shift, axis=1),
                    np.roll(scene.right, shift, axis=1),
                    i * PERIOD_NS,
                    i,
                    np.roll(scene.instance_mask, shift, axis=1),
                )
            )


class DecodeThenSleep:
    """The pacing `ReplaySource` had before: decode a frame, then sleep until its slot; never drop one."""

    def __init__(self, path: Path) -> None:
        from camera.sources import ReplaySource

        self.source = ReplaySource(path, pace="fast", loop=True)
        self.calibration = self.source.calibration
        self.dropped_late = 0
        self._start: tuple[int, int] | None = None  # (monotonic ns, stamp ns) of the first frame

    @property
    def is_lost(self) -> bool:
        return False

    def __iter__(self) -> DecodeThenSleep:
        return self

    def __next__(self) -> Any:
        frame = next(self.source)
        now = time.monotonic_ns()
        if self._start is None:
            self._start = (now, frame.timestamp_ns)
            return frame
        delay_ns = (frame.timestamp_ns - self._start[1]) - (now - self._start[0])
        if delay_ns > 0:
            time.sleep(delay_ns / 1e9)
        return frame

    def close(self) -> None:
        self.source.close()


class ReleaseLog:
    """Passes a source's frames on, noting when each left it: (timestamp ns, time.monotonic_ns())."""

    def __init__(self, source: Any, limit: int) -> None:
        self.source, self.limit = source, limit
        self.calibration = source.calibration
        self.releases: list[tuple[int, int]] = []

    @property
    def is_lost(self) -> bool:
        return False

    @property
    def dropped_late(self) -> int:
        return int(self.source.dropped_late)

    def __iter__(self) -> Iterator[Any]:
        return self

    def __next__(self) -> Any:
        if len(self.releases) + self.dropped_late >= self.limit:
            raise StopIteration
        frame = next(self.source)
        self.releases.append((frame.timestamp_ns, time.monotonic_ns()))
        return frame

    def close(self) -> None:
        self.source.close()


def hold_cpu(ms: float) -> None:
    """Keep this thread (and the GIL) busy for `ms` milliseconds."""
    end = time.perf_counter() + ms / 1e3
    while time.perf_counter() < end:
        pass


def spin() -> None:
    """A process that keeps one core busy until it is terminated."""
    while True:
        pass


def run_variant(name: str, recording: Path, frames: int, work_ms: float) -> dict[str, Any]:
    """Replay `frames` frames through a capture thread while the main thread works; the module docstring's figures."""
    from camera.sources import LatestFrameSource, ReplaySource

    inner = (
        DecodeThenSleep(recording)
        if name == "decode-then-sleep"
        else ReplaySource(recording, loop=True, max_late_ms=MAX_LATE_MS.get(name))
    )
    log = ReleaseLog(inner, frames)
    consumed = 0
    with LatestFrameSource(log) as latest:
        for _ in latest:
            consumed += 1
            hold_cpu(work_ms)
    (first_stamp, first_release), *_ = log.releases
    errors_ms = [((released - first_release) - (stamp - first_stamp)) / 1e6 for stamp, released in log.releases]
    return {
        "released": len(log.releases),
        "dropped_late": log.dropped_late,
        "consumed": consumed,
        "error_ms": {
            "p50": round(float(np.percentile(errors_ms, 50)), 2),
            "p95": round(float(np.percentile(errors_ms, 95)), 2),
            "max": round(max(errors_ms), 2),
        },
        "released_over_20ms_late": sum(e > LATE_MS for e in errors_ms),
        "last_frame_lag_ms": round(errors_ms[-1], 2),
    }


def main(argv: list[str] | None = None) -> int:
    """Run both variants under the same load; print the table, write `--json`."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recording", type=Path, default=DEFAULT_RECORDING, help="rendered once when missing")
    parser.add_argument("--frames", type=int, default=300, help="frames per variant (the recording loops)")
    parser.add_argument("--unique", type=int, default=30, help="frames of the rendered recording")
    parser.add_argument("--work-ms", type=float, default=40.0, help="consumer CPU time per frame, ms")
    parser.add_argument("--load", type=int, default=0, help="spinning processes started beside the replay")
    parser.add_argument("--variants", default="decode-then-sleep,recorded,recorded-20ms")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    args = parser.parse_args(argv)
    variants = args.variants.split(",")
    if unknown := set(variants) - {"decode-then-sleep", *MAX_LATE_MS}:
        parser.error(
            f"--variants: {', '.join(sorted(unknown))} unknown; expected decode-then-sleep, {', '.join(MAX_LATE_MS)}"
        )

    if not (args.recording / "recording.json").is_file():
        write_recording(args.recording, args.unique)
    load_average = os.getloadavg()[0]
    hogs = [multiprocessing.Process(target=spin, daemon=True) for _ in range(args.load)]
    for hog in hogs:
        hog.start()
    try:
        results = {name: run_variant(name, args.recording, args.frames, args.work_ms) for name in variants}
    finally:
        for hog in hogs:
            hog.terminate()
    baseline = results.get("decode-then-sleep")
    for row in results.values():
        if baseline is not None and row is not baseline:
            row["ratio_to_baseline"] = {
                k: round(row["error_ms"][k] / baseline["error_ms"][k], 3) if baseline["error_ms"][k] else None
                for k in ("p95", "max")
            }
    print(
        f"\nreplay pacing, {args.frames} frames at 15 fps of {args.recording.name}; "
        f"consumer {args.work_ms:g} ms/frame; "
        f"{args.load} spinning processes; load average {load_average:.2f} at the start\nCPU: {cpu_name()}\n"
    )
    print(
        f"{'variant':<18} {'released':>8} {'dropped':>7} {'p50 ms':>7} {'p95 ms':>7} {'max ms':>8} "
        f"{'>20ms':>6} {'last lag':>8}"
    )
    for name, row in results.items():
        e = row["error_ms"]
        print(
            f"{name:<18} {row['released']:8d} {row['dropped_late']:7d} {e['p50']:7.1f} {e['p95']:7.1f} {e['max']:8.1f} "
            f"{row['released_over_20ms_late']:6d} {row['last_frame_lag_ms']:8.1f}"
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        report = {
            "cpu": cpu_name(),
            "machine": cpu_description(),
            "load_average_1min_at_start": load_average,
            "settings": {"frames": args.frames, "work_ms": args.work_ms, "load": args.load, "fps": 15},
            "recording": str(args.recording),
            "variants": results,
        }
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
