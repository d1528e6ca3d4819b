"""CPU time of the onboard loop's two stages per frame, frame after frame without pacing or load shedding: what
the kernels cost, readable on a shared machine where `realtime.py`'s rates are not.

The shipped configuration (`--config`, default deploy/onboard_cpu.toml) on a `branchrange synth-flight`
recording without its masks (the configured segmenter finds the branches): each frame's `Pipeline.stereo_stage`
(coarse pass, segmenter network and instance steps, regions; the full-resolution instance step always on, as
at shedding level 0) and `Pipeline.geometry_stage` (branch disparity, cut points, tracking), each timed in this
process's CPU seconds (`time.process_time`: every thread, OpenCV's and onnxruntime's included; other processes'
load does not count, though it still slows a shared core's caches). Yardstick measured in the same run: the
coarse pass's SGBM alone on the same frames (half-resolution pair, `stereo.max_disp / 2`), code no kernel change
touches — compare two runs' stage times through it. Per-stage wall times (`timing_ms`, p50) are listed too;
on a loaded machine they include waiting for a core. Frames are decoded into memory first.

    .venv/bin/python benchmarks/stereo_stage_cpu.py --sequence out/bench/flight_hd720_150 --frames 40 \\
        --json out/stereo_stage_cpu.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from machine import cpu_description, cpu_name  # a script's own folder is on its import path


def cpu_ms(work: Any, *args: Any) -> tuple[Any, float]:
    """(what `work(*args)` returns, this process's CPU time it took, ms)."""
    start = time.process_time()
    result = work(*args)
    return result, 1000 * (time.process_time() - start)


def measure(sequence: Path, config: Path, frames: int, threads: int) -> dict[str, Any]:
    """Per-frame CPU ms (median, p90) of the stereo stage, the geometry stage and the yardstick, and the
    stereo stage's wall `timing_ms` p50s, over the first `frames` frames after a warm-up frame."""
    import cv2

    from branchrange.config.loader import load_config, pipeline_for
    from camera.sources import ReplaySource
    from stereo.backends import make_backend

    cv2.setNumThreads(threads)
    cfg = load_config(config)
    replay = ReplaySource(sequence, pace="fast", ignore_masks=True)
    pipeline = pipeline_for(cfg, replay.calibration)
    pairs = [(frame.left, frame.right) for _, frame in zip(range(frames + 1), replay)]
    replay.close()
    yardstick = make_backend("sgbm", max_disp=max(16, cfg.stereo.max_disp // 2))
    pipeline.process(*pairs[0])  # lazily built parts (backends, matchers) before the clock
    pipeline.reset()
    rows: dict[str, list[float]] = {"stereo_stage": [], "geometry_stage": [], "yardstick_coarse_sgbm": []}
    walls: dict[str, list[float]] = {}
    for left, right in pairs[1:]:
        stage, stereo_ms = cpu_ms(pipeline.stereo_stage, left, right)
        _, geometry_ms = cpu_ms(pipeline.geometry_stage, stage)
        small = [
            cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA)
            for image in (left, right)
        ]
        _, yardstick_ms = cpu_ms(yardstick.compute, *small)
        rows["stereo_stage"].append(stereo_ms)
        rows["geometry_stage"].append(geometry_ms)
        rows["yardstick_coarse_sgbm"].append(yardstick_ms)
        for name, ms in stage.timing_ms.items():
            walls.setdefault(name, []).append(ms)
    return {
        "cpu_ms": {name: spread(values) for name, values in rows.items()},
        "wall_ms_p50": {name: round(statistics.median(values), 1) for name, values in sorted(walls.items())},
    }


def spread(values: list[float]) -> dict[str, float]:
    """Median and p90 (nearest rank) of `values`, ms, rounded to 0.1."""
    ordered = sorted(values)
    return {"median": round(statistics.median(ordered), 1), "p90": round(ordered[int(0.9 * (len(ordered) - 1))], 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", type=Path, required=True, help="a `branchrange synth-flight` recording")
    parser.add_argument("--config", type=Path, default=Path("deploy/onboard_cpu.toml"), help="the deploy file")
    parser.add_argument("--frames", type=int, default=40, help="frames timed after the warm-up frame (default 40)")
    parser.add_argument("--threads", type=int, default=2, help="OpenCV threads (default 2)")
    parser.add_argument("--json", type=Path, help="write the report here")
    args = parser.parse_args(argv)
    if not (args.sequence / "recording.json").exists():
        print(f"--sequence {args.sequence}: no recording there (branchrange synth-flight --out DIR writes one)")
        return 2
    if args.frames < 1:
        parser.error("--frames must be at least 1")
    load = cpu_description()["load_average_1min"]
    report = {
        "cpu": cpu_name(),
        "load_average_1min": load,
        "config": str(args.config),
        "sequence": str(args.sequence),
        "threads": args.threads,
        **measure(args.sequence, args.config, args.frames, args.threads),
    }
    yardstick = report["cpu_ms"]["yardstick_coarse_sgbm"]["median"]
    print(f"{report['cpu']}, load {load}, {args.frames} frames, {args.threads} OpenCV threads — CPU ms per frame")
    print(f"{'stage':<24} {'median':>8} {'p90':>8} {'× yardstick':>12}")
    for name, row in report["cpu_ms"].items():
        print(f"{name:<24} {row['median']:>8.1f} {row['p90']:>8.1f} {row['median'] / yardstick:>12.2f}")
    print("wall p50 ms: " + "  ".join(f"{name} {ms}" for name, ms in report["wall_ms_p50"].items()))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
