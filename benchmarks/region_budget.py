"""Region budget benchmark: where each frame's time goes by range band, and what the budget changes.

The rendered approaches of `benchmarks/approach.py` (3 m → 0.8 m, HD720, cached under
out/bench/approach/) are run frame by frame through the pipeline the shipped deploy file describes
(`deploy/onboard_cpu.toml` read by the daemon's own loader, `pipeline_for`), with no pacing and no
threads: each frame's own compute, not the queueing the daemon adds (that is `approach.py`'s
capture → send). Each `--variant NAME=OVERRIDES` (`;`-separated `section.key=value`) is a pipeline of
its own, all fed the same frames in turn (the order rotating frame by frame), so a load change on the
shared machine touches every variant alike.

Reported per variant, masks source (`truth`: the recording's instance masks; `builtin`: the
configured segmenter) and 0.5 m band of the true range to the approach's target cut point at capture:
- `stage_ms`: p50 and p95 of each stage in `timing_ms` (the stereo half's `coarse_stereo`, `segment`,
  `roi_stereo`, `instances`/`refine`, and the geometry half's `masks`, `branch_disparity`, `trunk`,
  `cutpoints`, ...), and `total` (both halves); `stereo_half` = `stereo`+`rectify`, `geometry_half` = the rest;
- `error_mm`: each reported cut point to the nearest true cut point (camera frame of the capture), median
  and p90 over those within 5 cm of one (`right`), and how many were farther (`wrong`) — the accuracy
  the budget must not lose; `target_error_mm`: the same for the frame's target alone;
`--shed-level 1|2` runs every frame as the daemon's load shedding would (1: no full-resolution instances;
2: nor the branch refinement).
- `region_px`: p50 / max total pixels matched by the fine regions at their working scale, and
  `reduced`: the share of regions worked at a reduced scale (`roi.regions[].scale` > 1).

    .venv/bin/python benchmarks/region_budget.py --variant before=roi.budget=false --variant after= \\
        --json benchmarks/region_budget.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "benchmarks")]

from approach import BAND_EDGES_M, approach_target_id, band_label, band_of, render_flight  # noqa: E402
from machine import cpu_name  # noqa: E402

from branchrange.config.loader import Config, load_config, parse_override  # noqa: E402
from branchrange.core.frame_result import FrameResult  # noqa: E402
from branchrange.offline.flight import FlightTruth  # noqa: E402

DEPLOY_CONFIG = ROOT / "deploy" / "onboard_cpu.toml"
#: A cut point this close to a true one is right (the cut-point confidence's own definition), m.
RIGHT_WITHIN_M = 0.05
#: Stages of the stereo half (the rest of `timing_ms`, but `total`, is the geometry half's).
STEREO_STAGES = ("rectify", "stereo")


def variant_config(directory: Path, overrides: str) -> Config:
    """The deploy file for the recording `directory` with the variant's `;`-separated overrides."""
    items = ['camera.calibration=""', f'camera.source="replay:{directory}"']
    items += [item.strip() for item in overrides.split(";") if item.strip()]
    return load_config(DEPLOY_CONFIG, [parse_override(item) for item in items])


def frame_scores(result: FrameResult, truths: list[np.ndarray]) -> dict[str, Any]:
    """Per result: its stage times, each cut point's distance (m) to the nearest true one, the target's."""

    def nearest(point: np.ndarray) -> float:
        return min(float(np.linalg.norm(np.asarray(point) - t)) for t in truths)

    timing = dict(result.timing_ms)
    stereo = sum(timing.get(s, 0.0) for s in STEREO_STAGES)
    timing["stereo_half"] = stereo
    timing["geometry_half"] = timing.get("total", 0.0) - stereo
    regions = result.roi.regions if result.roi is not None else ()
    scales = [getattr(r, "scale", None) or 1 for r in regions]
    pixels = sum((r.box[2] - r.box[0]) * (r.box[3] - r.box[1]) // (s * s) for r, s in zip(regions, scales))
    target = result.target
    return {
        "timing": timing,
        "errors": [nearest(b.cut_point_m) for b in result.branches],
        "target_error": None if target is None else nearest(target.cut_point_m),
        "region_px": pixels,
        "regions": len(scales),
        "reduced": sum(s > 1 for s in scales),
    }


def percentile(values: list[float], q: float) -> float | None:
    """The q-th percentile, None for no values."""
    return round(float(np.percentile(values, q)), 1) if values else None


def summarise(frames: list[dict[str, Any]]) -> dict[str, Any]:
    """One band's figures (module docstring) from its frames' `frame_scores`."""
    stages: dict[str, list[float]] = defaultdict(list)
    for frame in frames:
        for stage, ms in frame["timing"].items():
            stages[stage].append(ms)
    errors = [e for f in frames for e in f["errors"]]
    right = [1000 * e for e in errors if e <= RIGHT_WITHIN_M]
    targets = [1000 * f["target_error"] for f in frames if f["target_error"] is not None]
    regions = sum(f["regions"] for f in frames)
    return {
        "frames": len(frames),
        "stage_ms": {s: {"p50": percentile(v, 50), "p95": percentile(v, 95)} for s, v in sorted(stages.items())},
        "error_mm": {
            "median": percentile(right, 50),
            "p90": percentile(right, 90),
            "right": len(right),
            "wrong": len(errors) - len(right),
        },
        "target_error_mm": {
            "median": percentile(targets, 50),
            "p90": percentile(targets, 90),
            "max": round(max(targets), 1) if targets else None,
            "count": len(targets),
        },
        "region_px": {
            "p50": percentile([f["region_px"] for f in frames], 50),
            "max": max((f["region_px"] for f in frames), default=None),
        },
        "reduced": round(sum(f["reduced"] for f in frames) / regions, 3) if regions else None,
    }


def run(directory: Path, variants: dict[str, str], masks: str, shed_level: int = 0) -> dict[str, Any]:
    """Every frame of the recording through each variant's pipeline (rotating order); per variant and band."""
    from branchrange.config.loader import pipeline_for
    from camera.sources.replay import ReplaySource

    truth = FlightTruth.load(directory)
    target_id = approach_target_id(directory)
    source = ReplaySource(directory, pace="fast", ignore_masks=masks != "truth")
    try:
        frames = list(source)
        calibration = source.calibration
    finally:
        source.close()
    pipelines = {name: pipeline_for(variant_config(directory, o), calibration) for name, o in variants.items()}
    for pipeline in pipelines.values():  # warm-up (model load, first-call allocations), then forget
        pipeline.process(frames[0].left, frames[0].right, mask=frames[0].mask)
        pipeline.reset()
    positions = {pose.index: i for i, pose in enumerate(truth.poses)}
    by_band: dict[str, dict[int, list[dict[str, Any]]]] = {name: defaultdict(list) for name in variants}
    names = list(variants)
    for n, frame in enumerate(frames):
        position = positions[frame.index]
        in_camera = truth.cut_points_in_camera(position)
        band = band_of(float(np.linalg.norm(in_camera[target_id])))
        for name in names[n % len(names) :] + names[: n % len(names)]:
            pipeline = pipelines[name]
            stage = pipeline.stereo_stage(
                frame.left, frame.right, frame.mask, frame.index, frame.timestamp_ns, shed_level
            )
            result = pipeline.geometry_stage(stage)
            by_band[name][band].append(frame_scores(result, list(in_camera.values())))
    bands = range(len(BAND_EDGES_M) - 1)
    return {name: {band_label(b): summarise(by_band[name][b]) for b in bands} for name in names}


def print_report(report: dict[str, Any]) -> None:
    """Per masks source: stage p50/p95 by band for each variant, then the accuracy by band."""
    print(f"CPU: {report['cpu']}; {report['threads']} threads; load {report['load_before']} → {report['load_after']}")
    for flight, by_masks in report["flights"].items():
        for masks, by_variant in by_masks.items():
            print(f"\n{flight}, {masks} masks — stage ms p50/p95 by range band")
            bands = list(next(iter(by_variant.values())))
            for name, by_band in by_variant.items():
                stages = sorted({s for b in by_band.values() for s in b["stage_ms"]})
                print(f"  [{name}] {'stage':>16} " + " ".join(f"{b + ' m':>14}" for b in bands))
                for stage in stages:
                    cells = [by_band[b]["stage_ms"].get(stage, {"p50": None, "p95": None}) for b in bands]
                    print(
                        f"  {'':>{len(name) + 2}} {stage:>16} "
                        + " ".join(f"{fmt(c['p50'])}/{fmt(c['p95']):<6}".rjust(14) for c in cells)
                    )
                region = [f"{fmt(by_band[b]['region_px']['p50'], 0)}" for b in bands]
                reduced = [fmt(by_band[b]["reduced"], 2) for b in bands]
                print(f"  {'':>{len(name) + 2}} {'region px p50':>16} " + " ".join(f"{c:>14}" for c in region))
                print(f"  {'':>{len(name) + 2}} {'reduced share':>16} " + " ".join(f"{c:>14}" for c in reduced))
            print("  accuracy: cut points within 5 cm, median/p90 mm (right, wrong); target median/p90/max mm")
            for name, by_band in by_variant.items():
                cells = []
                for b in bands:
                    e, t = by_band[b]["error_mm"], by_band[b]["target_error_mm"]
                    cells.append(
                        f"{fmt(e['median'])}/{fmt(e['p90'])} ({e['right']},{e['wrong']}) "
                        f"{fmt(t['median'])}/{fmt(t['p90'])}/{fmt(t['max'])}"
                    )
                print(f"  [{name}] " + " | ".join(cells))


def fmt(value: Any, digits: int = 1) -> str:
    """A number, `—` for None."""
    return "—" if value is None else f"{value:.{digits}f}"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line (module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME=OVERRIDES",
        help="a pipeline: `;`-separated section.key=value overrides of the deploy file (repeatable)",
    )
    parser.add_argument("--speeds", default="0.5", help="approach speeds, m/s (comma-separated; rendered once)")
    parser.add_argument("--masks", choices=("truth", "builtin", "both"), default="both")
    parser.add_argument("--resolution", default="1280x720")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--threads", type=int, default=2, help="OpenCV and torch threads")
    parser.add_argument("--json", type=Path, help="write the report here")
    parser.add_argument(
        "--shed-level", type=int, default=0, choices=(0, 1, 2), help="the daemon's load shedding level for every frame"
    )
    args = parser.parse_args(argv)
    args.variants = {}
    for item in args.variant or ["shipped="]:
        name, _, overrides = item.partition("=")
        if not name:
            parser.error(f"--variant {item!r}: expected NAME=OVERRIDES")
        args.variants[name] = overrides
    return args


def main(argv: list[str] | None = None) -> int:
    """Run every flight, masks source and variant; print; write `--json`."""
    import cv2
    import torch

    args = parse_args(argv)
    cv2.setNumThreads(args.threads)
    torch.set_num_threads(args.threads)
    masks = ["truth", "builtin"] if args.masks == "both" else [args.masks]
    load = " ".join(f"{v:.1f}" for v in os.getloadavg())
    report: dict[str, Any] = {
        "cpu": cpu_name(),
        "threads": args.threads,
        "load_before": load,
        "variants": args.variants,
        "shed_level": args.shed_level,
        "config": str(DEPLOY_CONFIG.relative_to(ROOT)),
        "flights": {},
    }
    started = time.time()
    for speed in [float(v) for v in args.speeds.split(",")]:
        directory = render_flight(args.resolution, speed, 0.0, args.seed)
        report["flights"][directory.name] = {m: run(directory, args.variants, m, args.shed_level) for m in masks}
    report["load_after"] = " ".join(f"{v:.1f}" for v in os.getloadavg())
    report["wall_s"] = round(time.time() - started, 1)
    print_report(report)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
