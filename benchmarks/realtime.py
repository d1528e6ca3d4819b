"""Real-time onboard benchmark: a flight sequence replayed at its own frame rate through the daemon.

Each frame is released at its recorded timestamp (as a 15 fps camera would deliver it; decoding
starts ahead of the release, as a camera delivers raw frames, and a frame that cannot be on time is
dropped: `camera.sources.ReplaySource`), and goes through the daemon's own
code path — `branchrange.onboard.daemon.Daemon` with its capture, stereo and geometry+send threads, the
pipeline of `branchrange.core.frame_results.pipeline_for` and a real `MavlinkRelay` sending to a UDP
socket on 127.0.0.1 — on `--threads` CPU threads (OpenCV and torch). Nothing waits for the slow
stage: frames the daemon has no time for are dropped, as onboard.

Modes (`--modes`, comma-separated):
- `full-sgbm`   — whole-frame SGBM at full resolution (`stereo.mode = "full"`): the baseline, measured in the same run;
- `roi-sgbm`    — coarse pass + per-branch full-resolution SGBM regions (`stereo.mode = "roi"`);
- `roi-emcstereo` — coarse SGBM pass + per-branch EMCStereo regions (`--weights`, else random weights: timing only).
`--segmenter truth` uses the sequence's instance masks, `builtin` ignores them and runs the built-in
segmenter; `both` runs each mode twice.

Keys of `--json FILE` (one entry per mode and segmenter under `modes`, e.g. `modes["roi-sgbm/truth"]`):
- `fresh_rate_hz`: results published with capture → publish age ≤ `max_result_age_s` (0.5 s), per
  second of sequence time — what the autopilot gets as targets;
- `latency_ms.{p50,p95,max}`: capture → publish, milliseconds, over published results;
- `frames_processed`, `frames_dropped` (camera frames the stereo stage had no time for, plus stereo
  outputs the geometry stage had no time for, plus frames the replay could not release on time: a
  busy machine's decoding), `frames_released`;
- `target_error_m.{median,p90}`: the published target against the nearest true cut point, both in
  the camera frame at the frame's capture (the truth of `flight.json` at that frame's pose);
- `target_recall`: processed frames with a target / processed frames whose truth has a visible cut point;
- `false_target_rate`: targets farther than 10 cm from every true cut point / targets published;
- `stage_ms.<stage>.p50`: per-stage compute time (the result's `timing_ms`);
- `handover_ms.{capture_to_stereo_ms,capture_to_geometry_ms,capture_to_publish_ms}.p50`: when the
  frame reached each thread (the result's `latency`): the waits between the stages;
- `ratio_to_baseline.{fresh_rate,latency_p50}`: against `full-sgbm` with the same segmenter.
Also `cpu` (model and vector extensions), `threads`, `sequence`, `max_result_age_s`.

    .venv/bin/python benchmarks/realtime.py --json out/realtime.json   # renders a default HD720 flight first
    .venv/bin/python benchmarks/realtime.py --sequence out/flight --modes roi-sgbm --segmenter builtin
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import socket
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from machine import cpu_name  # a script's own folder is on its import path

if TYPE_CHECKING:
    from branchrange.core.frame_result import FrameResult

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SEQUENCE = ROOT / "out" / "bench" / "flight_hd720"
MODES = {  # mode → ([stereo] backend, mode)
    "full-sgbm": ("sgbm", "full"),
    "roi-sgbm": ("sgbm", "roi"),
    "roi-emcstereo": ("emcstereo", "roi"),
}
FALSE_TARGET_M = 0.10


class UdpSink:
    """A UDP socket on 127.0.0.1 that reads and discards what the relay sends (the flight controller's place)."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.datagrams = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _drain(self) -> None:
        while not self._stop.is_set():
            try:
                self.sock.recv(65536)
                self.datagrams += 1
            except OSError:
                continue

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()


def percentile(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def render_default_sequence(path: Path) -> None:
    """The default flight: HD720, 15 fps, 3.0 → 0.8 m (`branchrange synth-flight` defaults)."""
    from branchrange.cli import main as branchrange_main

    print(f"rendering the default flight sequence into {path} (once) ...", file=sys.stderr)
    code = branchrange_main(["synth-flight", "--out", str(path), "--seed", "1"])
    if code != 0:
        raise SystemExit(f"synth-flight failed with exit code {code}")


def run_mode(sequence: Path, mode: str, segmenter: str, args: argparse.Namespace, truth: Any) -> dict[str, Any]:
    """Replay `sequence` in real time through the daemon in one mode; the metrics of the module docstring."""
    from branchrange.core.config import (
        CameraConfig,
        LogConfig,
        MavlinkConfig,
        load_config,
        parse_override,
    )
    from branchrange.core.frame_results import pipeline_for
    from branchrange.onboard.daemon import Daemon
    from branchrange.onboard.mavlink import CameraMount, MavlinkRelay
    from camera.sources import ReplaySource

    backend, stereo_mode = MODES[mode]
    weights = args.weights or ""
    if backend == "emcstereo" and not weights:
        weights = str(random_weights(args))
    sink = UdpSink()
    loaded = load_config(None, [parse_override(item) for item in args.set])  # e.g. the segmenter's settings
    cfg = dataclasses.replace(
        loaded,
        camera=CameraConfig(source=f"replay:{sequence}"),
        stereo=dataclasses.replace(
            loaded.stereo, backend=backend, weights=weights, max_disp=args.max_disp, mode=stereo_mode
        ),
        log=LogConfig(status_interval_s=3600.0),
        mavlink=MavlinkConfig(url=f"udpout:127.0.0.1:{sink.port}", max_result_age_s=args.max_result_age_s),
    )

    def open_source() -> Any:
        return ReplaySource(sequence, pace="recorded", ignore_masks=segmenter != "truth")

    probe = ReplaySource(sequence, pace="fast")
    pipeline = pipeline_for(cfg, probe.calibration)
    warm = next(probe)  # build lazily created parts (backends, coarse matchers) before the clock starts
    pipeline.process(warm.left, warm.right, mask=warm.mask if segmenter == "truth" else None)
    pipeline.reset()
    probe.close()
    relay = MavlinkRelay(cfg.mavlink, CameraMount.from_rpy())
    published: list[FrameResult] = []
    daemon = Daemon(
        cfg,
        open_source=open_source,
        pipeline=pipeline,
        relay=relay,
        observers=[lambda result, _artifacts: published.append(result)],
    )
    started = time.monotonic()
    try:
        daemon.run()
    finally:
        daemon.close()
        sink.close()
    wall_s = time.monotonic() - started
    return summarise(published, daemon, truth, args.max_result_age_s, wall_s)


def random_weights(args: argparse.Namespace) -> Path:
    """A checkpoint of a randomly initialised EMCStereo (timing only), written once under out/bench."""
    import torch

    from stereo import EMCStereo, save_checkpoint

    path = ROOT / "out" / "bench" / "emcstereo_random.pth"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(0)
        save_checkpoint(EMCStereo(), path)
    print("roi-emcstereo: random weights (timing only; its errors mean nothing)", file=sys.stderr)
    return path


def summarise(published: list[FrameResult], daemon: Any, truth: Any, max_age_s: float, wall_s: float) -> dict[str, Any]:
    """The docstring's metrics from the published results and the daemon's counters."""
    ages = [r.latency.capture_to_publish_ms for r in published if r.latency is not None]
    positions = {pose.index: i for i, pose in enumerate(truth.poses)}
    duration_s = (truth.poses[-1].timestamp_ns - truth.poses[0].timestamp_ns) / 1e9 + 1 / fps_of(truth)
    errors, false_targets, targets, with_truth, hits = [], 0, 0, 0, 0
    for result in published:
        position = positions.get(result.frame.index)
        if position is None:
            continue
        pose = truth.poses[position]
        true_points = list(truth.cut_points_in_camera(position).values())
        visible = bool(pose.visible_cut_ids)
        with_truth += visible
        target = result.target
        if target is None or not true_points:
            continue
        targets += 1
        hits += visible
        error = min(float(np.linalg.norm(np.asarray(target.cut_point_m) - p)) for p in true_points)
        errors.append(error)
        false_targets += error > FALSE_TARGET_M
    stages: dict[str, list[float]] = {}
    for result in published:
        for stage, ms in result.timing_ms.items():
            stages.setdefault(stage, []).append(ms)
    fresh = sum(age <= 1000 * max_age_s for age in ages)
    return {
        "fresh_rate_hz": round(fresh / duration_s, 3),
        "latency_ms": {"p50": percentile(ages, 50), "p95": percentile(ages, 95), "max": max(ages, default=None)},
        "frames_released": len(truth.poses),
        "frames_processed": len(published),
        "frames_dropped": int(daemon.dropped + daemon.skipped + daemon.dropped_late),
        "target_error_m": {"median": percentile(errors, 50), "p90": percentile(errors, 90)},
        "target_recall": round(hits / with_truth, 4) if with_truth else None,
        "false_target_rate": round(false_targets / targets, 4) if targets else None,
        "stage_ms": {stage: {"p50": percentile(values, 50)} for stage, values in sorted(stages.items())},
        "handover_ms": {
            key: {"p50": percentile([getattr(r.latency, key) for r in published if r.latency is not None], 50)}
            for key in ("capture_to_stereo_ms", "capture_to_geometry_ms", "capture_to_publish_ms")
        },
        "wall_s": round(wall_s, 2),
    }


def fps_of(truth: Any) -> float:
    """Frames per second of the sequence from its poses' timestamps."""
    stamps = [p.timestamp_ns for p in truth.poses]
    return 1e9 / statistics.median(np.diff(stamps)) if len(stamps) > 1 else 15.0


def fmt(value: Any, scale: float = 1.0, digits: int = 0) -> str:
    return "—" if value is None else f"{value * scale:.{digits}f}"


def print_table(report: dict[str, Any]) -> None:
    print(
        f"\nreal-time replay of {report['sequence']} on {report['cpu']}, {report['threads']} threads, "
        f"max_result_age_s {report['max_result_age_s']}"
    )
    header = (
        f"{'mode/segmenter':24} {'fresh Hz':>8} {'p50 ms':>7} {'p95 ms':>7} {'max ms':>7} {'proc':>5} {'drop':>5} "
        f"{'err med cm':>10} {'err p90 cm':>10} {'recall':>6} {'false':>6} {'× fresh':>7} {'× p50':>6}"
    )
    print(header)
    print("-" * len(header))
    for name, row in report["modes"].items():
        ratio = row.get("ratio_to_baseline", {})
        print(
            f"{name:24} {row['fresh_rate_hz']:8.2f} "
            f"{fmt(row['latency_ms']['p50']):>7} {fmt(row['latency_ms']['p95']):>7} "
            f"{fmt(row['latency_ms']['max']):>7} {row['frames_processed']:5d} {row['frames_dropped']:5d} "
            f"{fmt(row['target_error_m']['median'], 100, 1):>10} {fmt(row['target_error_m']['p90'], 100, 1):>10} "
            f"{fmt(row['target_recall'], 1, 2):>6} {fmt(row['false_target_rate'], 1, 2):>6} "
            f"{fmt(ratio.get('fresh_rate'), 1, 2):>7} {fmt(ratio.get('latency_p50'), 1, 2):>6}"
        )
    print("\nper-stage p50 (ms):")
    for name, row in report["modes"].items():
        print(f"  {name:24} " + "  ".join(f"{stage} {fmt(v['p50'], 1, 1)}" for stage, v in row["stage_ms"].items()))
    print("\nframe arrival → each hand-over, p50 (ms):")
    for name, row in report["modes"].items():
        print(
            f"  {name:24} "
            + "  ".join(f"{key.removesuffix('_ms')} {fmt(v['p50'], 1, 1)}" for key, v in row["handover_ms"].items())
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequence", type=Path, help=f"a flight recording (default: render {DEFAULT_SEQUENCE} once)")
    parser.add_argument(
        "--modes", default="full-sgbm,roi-sgbm,roi-emcstereo", help=f"comma-separated: {', '.join(MODES)}"
    )
    parser.add_argument("--segmenter", choices=("truth", "builtin", "both"), default="both")
    parser.add_argument(
        "--weights", help="EMCStereo checkpoint for roi-emcstereo (default: random weights, timing only)"
    )
    parser.add_argument("--max-disp", type=int, default=128, help="full-resolution disparity range, px")
    parser.add_argument("--max-result-age-s", type=float, default=0.5)
    parser.add_argument("--threads", type=int, default=2, help="OpenCV and torch threads")
    parser.add_argument("--json", type=Path, help="write the report here")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="a config override for every run, e.g. --set segmenter.learned.precision=int8 (repeatable)",
    )
    args = parser.parse_args(argv)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        parser.error(f"unknown mode {unknown[0]!r}; expected {', '.join(MODES)}")

    import cv2
    import torch

    from branchrange.offline.flight import FlightTruth

    cv2.setNumThreads(args.threads)
    torch.set_num_threads(args.threads)
    sequence = args.sequence or DEFAULT_SEQUENCE
    if args.sequence is None and not (sequence / "flight.json").exists():
        render_default_sequence(sequence)
    truth = FlightTruth.load(sequence)
    segmenters = ["truth", "builtin"] if args.segmenter == "both" else [args.segmenter]
    report: dict[str, Any] = {
        "cpu": cpu_name(),
        "threads": args.threads,
        "sequence": str(sequence),
        "max_result_age_s": args.max_result_age_s,
        "max_disp": args.max_disp,
        "overrides": args.set,
        "modes": {},
    }
    for segmenter in segmenters:
        for mode in modes:
            print(f"{mode}/{segmenter} ...", file=sys.stderr)
            report["modes"][f"{mode}/{segmenter}"] = run_mode(sequence, mode, segmenter, args, truth)
        baseline = report["modes"].get(f"full-sgbm/{segmenter}")
        if baseline:
            for mode in modes:
                row = report["modes"][f"{mode}/{segmenter}"]
                row["ratio_to_baseline"] = {
                    "fresh_rate": round(row["fresh_rate_hz"] / baseline["fresh_rate_hz"], 2)
                    if baseline["fresh_rate_hz"]
                    else None,
                    "latency_p50": round(row["latency_ms"]["p50"] / baseline["latency_ms"]["p50"], 3)
                    if row["latency_ms"]["p50"] and baseline["latency_ms"]["p50"]
                    else None,
                }
    print_table(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
