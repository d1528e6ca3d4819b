"""Which cut-point confidence is enough to fence an obstacle: confidence against error on synthetic scenes.

For every cut point the pipeline estimates on a synthetic set (`emcstereo synth`), sgbm stereo, with
the set's masks and with the built-in segmenter, the 3D distance to the nearest true cut point
(visible or not) in the same frame. An obstacle that is wrong by more than `--misplaced-m` (20 cm:
far more than the 5 cm recall radius, about the size of the avoidance margin's slack) fences off
space that is free, or leaves a branch where none is reported. For thresholds 0 … 0.6 the table
shows how many of the cut points within 5 cm of a true one survive (obstacles kept) and how many of
the misplaced ones still get through. `mavlink.obstacle_min_confidence` defaults to the value this
table supports (docs/mavlink.md, "Obstacle confidence").

    .venv/bin/python -m stereo.cli synth --out /tmp/evalset --scenes 40 --seed 0 --size 640x360
    .venv/bin/python benchmarks/obstacle_confidence.py /tmp/evalset --json out/obstacle_confidence.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from branchrange.core.pipeline import Pipeline, untracked_whole_frame  # noqa: E402
from branchrange.offline.evaluate_cuts import RECALL_RADIUS_M, read_frame, scene_indices  # noqa: E402

THRESHOLDS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)


def cut_point_errors(root: Path, limit: int | None, max_disp: int) -> dict[str, list[tuple[float, float]]]:
    """(confidence, error to the nearest true cut point in m) of every estimated cut point, per mask mode."""
    from stereo.backends import make_backend

    backend = make_backend("sgbm", max_disp=max_disp)
    samples: dict[str, list[tuple[float, float]]] = {"gt": [], "segmenter": []}
    for index in scene_indices(root)[:limit]:
        frame = read_frame(root, index)
        pipeline = Pipeline(
            untracked_whole_frame(max_disp),
            focal_px=frame.focal_px,
            baseline_m=frame.baseline_m,
            principal_point=frame.principal_point,
        )
        stereo = backend.compute(frame.left, frame.right)
        truth = [np.asarray(b["cut_point_m"], dtype=np.float64) for b in frame.branches]
        for masks in samples:
            result = pipeline.process_disparity(
                frame.left,
                stereo.disparity,
                stereo.confidence,
                mask=frame.mask if masks == "gt" else None,
                backend="sgbm",
                right=frame.right,
            )
            for b in result.branches:
                error = min(float(np.linalg.norm(np.asarray(b.cut_point_m) - t)) for t in truth)
                samples[masks].append((b.confidence, error))
    return samples


def table(samples: list[tuple[float, float]], misplaced_m: float) -> list[dict[str, float]]:
    """Per threshold: share of good cut points (≤ 5 cm) kept, share of misplaced ones (> misplaced_m) kept."""
    conf = np.array([c for c, _ in samples])
    err = np.array([e for _, e in samples])
    good, bad = err <= RECALL_RADIUS_M, err > misplaced_m
    rows = []
    for t in THRESHOLDS:
        kept = conf >= t
        rows.append(
            {
                "threshold": t,
                "good_kept": round(float(kept[good].mean()), 3) if good.any() else None,
                "misplaced_kept": round(float(kept[bad].mean()), 3) if bad.any() else None,
                "misplaced_share_of_kept": round(float(bad[kept].mean()), 3) if kept.any() else None,
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="a synthetic set written by `emcstereo synth`")
    parser.add_argument("--limit", type=int, help="first N scenes only")
    parser.add_argument("--max-disp", type=int, default=128)
    parser.add_argument("--misplaced-m", type=float, default=0.20)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    samples = cut_point_errors(args.root, args.limit, args.max_disp)
    report = {
        "set": str(args.root),
        "misplaced_m": args.misplaced_m,
        "masks": {m: {"cut_points": len(s), "rows": table(s, args.misplaced_m)} for m, s in samples.items()},
    }
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))
    print(
        f"cut point misplaced: more than {args.misplaced_m} m from every true cut point; "
        f"good: within {RECALL_RADIUS_M} m"
    )
    for masks, entry in report["masks"].items():
        print(f"sgbm + {masks} masks: {entry['cut_points']} cut points")
        print(f"{'min conf.':>9} {'good kept':>10} {'misplaced kept':>15} {'misplaced share of kept':>24}")
        for r in entry["rows"]:
            print(
                f"{r['threshold']:>9} {r['good_kept']!s:>10} {r['misplaced_kept']!s:>15} "
                f"{r['misplaced_share_of_kept']!s:>24}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
