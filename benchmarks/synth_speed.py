"""Speed of the synthetic scene generator: one stereo pair at several sizes, and a whole dataset.

The baseline, measured in the same run, is the ground-truth pass alone (one ray per pixel, no
shading) at each size: the least any render of that scene must cost. Wall and CPU seconds are
both printed; on a shared machine the wall time depends on what else runs. `--json` also writes the
rows, with the CPU (`machine.py`).

    .venv/bin/python benchmarks/synth_speed.py                        # pairs + 100 scenes at 640×360
    .venv/bin/python benchmarks/synth_speed.py --dataset-scenes 0     # pairs only
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from machine import cpu_name  # a script's own folder is on its import path

from stereo.synth import SynthCamera, SynthOptions, render_scene
from stereo.synth.camera import RayGrid
from stereo.synth.render import rasterise, scene_batches
from stereo.synth.scene import build_scene
from stereo.synth.writer import write_dataset


def timed(function: Callable[..., object], *args: object, **kwargs: object) -> tuple[float, float]:
    """(wall s, CPU s of this process, all threads) of one call."""
    wall, cpu = time.perf_counter(), time.process_time()
    function(*args, **kwargs)
    return time.perf_counter() - wall, time.process_time() - cpu


def truth_pass(seed: int, camera: SynthCamera) -> None:
    """The baseline: draw the scene and cast one ray per left pixel without shading."""
    scene = build_scene(np.random.default_rng(seed), camera, SynthOptions())
    rasterise(scene_batches(scene, camera), RayGrid.for_view(camera, "left", 1), None, None)


def pair_rows(sizes: list[tuple[int, int]], seeds: list[int]) -> list[tuple[str, str, float, float]]:
    """(size, configuration, median wall s, median CPU s) over the seeds."""
    rows = []
    for width, height in sizes:
        camera = SynthCamera.zed_mini(width, height)
        configs = [
            ("truth pass only (baseline)", lambda s, c=camera: truth_pass(s, c)),
            ("pair, 2x2 rays/px, 1 thread", lambda s, c=camera: render_scene(s, c, threads=1)),
            ("pair, 2x2 rays/px, 2 threads", lambda s, c=camera: render_scene(s, c, threads=2)),
        ]
        for name, run in configs:
            times = [timed(run, seed) for seed in seeds]
            rows.append(
                (
                    f"{width}x{height}",
                    name,
                    statistics.median(t[0] for t in times),
                    statistics.median(t[1] for t in times),
                )
            )
    return rows


def main() -> None:
    """Print the pair and dataset timings."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3, help="scenes per pair measurement (median)")
    parser.add_argument("--dataset-scenes", type=int, default=100, help="scenes of the dataset run (0: skip)")
    parser.add_argument("--workers", type=int, default=2, help="processes for the dataset run")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args()
    seeds = list(range(args.seeds))
    rows = pair_rows([(640, 360), (1280, 720)], seeds)
    print(f"CPU: {cpu_name()}; median of {args.seeds} scenes per row")
    print(f"{'size':<10} {'what':<30} {'wall s':>8} {'CPU s':>8}")
    for size, name, wall, cpu in rows:
        print(f"{size:<10} {name:<30} {wall:>8.2f} {cpu:>8.2f}")
    report: dict = {
        "cpu": cpu_name(),
        "pairs": [{"size": size, "what": name, "wall_s": wall, "cpu_s": cpu} for size, name, wall, cpu in rows],
    }
    if args.dataset_scenes:
        with tempfile.TemporaryDirectory() as out:
            wall, cpu = timed(write_dataset, out, args.dataset_scenes, 0, 640, 360, workers=args.workers)
        print(
            f"{'640x360':<10} {f'{args.dataset_scenes} scenes, {args.workers} workers':<30} {wall:>8.1f} "
            f"{'(children)':>8}  = {wall / args.dataset_scenes:.2f} s/scene"
        )
        report["dataset"] = {"scenes": args.dataset_scenes, "workers": args.workers, "wall_s": wall}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2), encoding="utf-8")


if __name__ == "__main__":
    main()
