"""`branchrange demo`: render a synthetic branch scene, run the whole pipeline, compare with the truth.

The scene comes from the generator (`stereo.synth`, exact ground truth); its instance mask stands
in for a mask file unless --segmenter [NAME] asks for a segmenter. Prints every truth branch's cut
point next to the estimate and writes the overlay, the result JSON and the pair to --out.
Without --weights the stereo backend is sgbm (said so on the first line); with weights, EMCStereo.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from branchrange.commands.estimate import (
    EXIT_BAD_INPUT,
    add_segmenter_arguments,
    add_stereo_arguments,
    branch_table,
    segmenter_settings,
    whole_frame_stereo,
)

if TYPE_CHECKING:
    from branchrange.core.frame_result import FrameResult

DEMO_SEED = 6


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `demo` to the `branchrange` command."""
    p = subparsers.add_parser(
        "demo", help="synthetic scene → whole pipeline → cut points vs truth", description=__doc__
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    p.add_argument("--seed", type=int, default=DEMO_SEED, help=f"scene seed (default {DEMO_SEED})")
    p.add_argument("--size", default="640x360", help="WIDTHxHEIGHT of the rendered pair (default 640x360)")
    add_segmenter_arguments(p, optional_value=True)
    add_stereo_arguments(p, None)
    p.set_defaults(func=run)


def truth_table(result: FrameResult, truth: list) -> str:
    """Each truth branch with a visible cut point next to its estimate (nearest within 25 cm)."""
    estimates = [(b, np.asarray(b.cut_point_m)) for b in result.branches]
    rows = [
        f"{'truth':>5} {'est id':>6}  {'estimated cut (m)':>23}  {'true cut (m)':>23} "
        f"{'3D err cm':>9} {'dist est':>8} {'dist true':>9} {'dist err':>8}"
    ]
    errors = []
    for branch in truth:
        if not branch.cut_visible:
            continue
        true_point = np.asarray(branch.cut_point_m)
        true_distance = float(np.linalg.norm(true_point))
        match = min(estimates, key=lambda e: np.linalg.norm(e[1] - true_point), default=None)
        xyz = " ".join(f"{v:7.3f}" for v in true_point)
        if match is None or np.linalg.norm(match[1] - true_point) > 0.25:
            rows.append(
                f"{branch.id:>5} {'-':>6}  {'(not found)':>23}  {xyz:>23} {'-':>9} {'-':>8} "
                f"{true_distance:>9.3f} {'-':>8}"
            )
            continue
        est, point = match
        error = float(np.linalg.norm(point - true_point))
        errors.append(error)
        pct = 100.0 * (est.distance_m - true_distance) / true_distance
        rows.append(
            f"{branch.id:>5} {est.id:>6}  {' '.join(f'{v:7.3f}' for v in point):>23}  {xyz:>23} "
            f"{100 * error:>9.2f} {est.distance_m:>8.3f} {true_distance:>9.3f} {pct:>7.2f}%"
        )
    visible = sum(1 for b in truth if b.cut_visible)
    if errors:
        rows.append(
            f"{sum(e <= 0.05 for e in errors)} of {visible} visible cut points within 5 cm; "
            f"median 3D error {100 * float(np.median(errors)):.2f} cm"
        )
    return "\n".join(rows)


def run(args: argparse.Namespace) -> int:
    """Render, run, print, write."""
    from branchrange.core.cutpoints import CutPointConfig
    from branchrange.core.overlay import write_overlay
    from branchrange.core.pipeline import Pipeline, PipelineConfig
    from stereo.commands.synth import parse_size
    from stereo.io import write_rgb
    from stereo.synth import SynthCamera, render_scene

    try:
        width, height = parse_size(args.size)
        config = PipelineConfig(
            stereo=whole_frame_stereo(args),
            cutpoints=CutPointConfig(tracking=False),
            segmenter=segmenter_settings(args),
        )
        segmenter = config.segmenter.build()  # before rendering
    except (ValueError, argparse.ArgumentTypeError) as exc:
        print(f"branchrange demo: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.weights is None:
        print("no --weights given: using the classical sgbm stereo backend (pass --weights W for EMCStereo)")
    else:
        print(f"stereo backend: {config.stereo.backend} with weights {args.weights}")
    start = time.perf_counter()
    scene = render_scene(args.seed, SynthCamera.zed_mini(width, height))
    print(
        f"rendered scene {args.seed} ({width}×{height}, {scene.pose} view, {scene.foliage} foliage, "
        f"f = {scene.camera.focal_px:g} px, B = {scene.camera.baseline_m} m) in {time.perf_counter() - start:.1f} s"
    )
    pipeline = Pipeline(
        config,
        focal_px=scene.camera.focal_px,
        baseline_m=scene.camera.baseline_m,
        principal_point=(scene.camera.cx, scene.camera.cy),
        segmenter=segmenter,
    )
    try:
        result = pipeline.process(scene.left, scene.right, mask=None if args.segmenter else scene.instance_mask)
    except (ValueError, OSError) as exc:
        print(f"branchrange demo: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    timing = result.timing_ms
    print(
        f"pipeline: {timing['total']:.0f} ms (stereo {timing['stereo']:.0f} ms, masks {timing['masks']:.0f} ms, "
        f"cut points {timing['cutpoints']:.0f} ms); masks from "
        f"{'the ' + pipeline.segmenter.name + ' segmenter' if args.segmenter else 'the truth mask'}"
    )
    print()
    print(branch_table(result))
    print()
    print(truth_table(result, scene.branches))
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        write_rgb(args.out / "left.png", scene.left)
        write_rgb(args.out / "right.png", scene.right)
        (args.out / "result.json").write_text(json.dumps(result.to_json_dict(), indent=1) + "\n", encoding="utf-8")
        overlay = write_overlay(args.out / "overlay.png", pipeline.last.left, result, pipeline.last.masks)
    except (ValueError, OSError) as exc:
        print(f"branchrange demo: error: cannot write the outputs to {args.out}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"\nwrote {overlay}, {args.out / 'result.json'}, left.png, right.png")
    return 0
