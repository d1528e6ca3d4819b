"""Range-limited EMCStereo inference: latency and accuracy at max_disp 192 / 96 / 64, one run.

For a known working range (a pruning tool works at 0.3–2 m), a smaller disparity search range
shrinks the cost volume and the 3D work. This prints, per range, the median latency of the fast
path at one image size and the accuracy of the given weights on held-out synthetic scenes and on
the real pairs of ../shared/data/stereo: over all valid pixels (gt < 192: what a shorter range
gives up) and over the pixels inside the range (gt < 64: what it changes where it can still see).
The 192 row is the baseline measured in the same run. `--json` also writes the rows, with the CPU
(`machine.py`) and the settings.

    python benchmarks/range_limited.py --weights runs/x/best.pth [--scenes 4] [--size 384x1248] [--json F]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from machine import cpu_name  # a script's own folder is on its import path

from stereo.backends import make_backend
from stereo.datasets.middlebury import MiddleburyDataset
from stereo.io import read_pfm, read_rgb
from stereo.metrics import MetricAverager
from stereo.synth import SynthCamera, render_scene

SHARED_STEREO = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "stereo"
RANGES = (192, 96, 64)
WORKING_RANGE = 64


def synthetic_pairs(count: int, seed: int, width: int, height: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Held-out synthetic scenes (seeds far from any training seed): left, right, true disparity."""
    camera = SynthCamera.zed_mini(width, height)
    scenes = [render_scene(seed + i, camera) for i in range(count)]
    return [(s.left, s.right, s.disparity) for s in scenes]


def real_pairs() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Tsukuba, Venus and the SceneFlow frame, when ../shared/data is present."""
    pairs = []
    for name in ("middlebury2001_tsukuba", "middlebury2001_venus"):
        if (SHARED_STEREO / name).is_dir():
            sample = MiddleburyDataset(SHARED_STEREO / name)[0]
            pairs.append((sample["left"], sample["right"], sample["disparity"]))
    flying = SHARED_STEREO / "sceneflow_flyingthings3d_train_A_0000_0006"
    if flying.is_dir():
        pairs.append(
            (
                read_rgb(flying / "left_cleanpass.png"),
                read_rgb(flying / "right_cleanpass.png"),
                read_pfm(flying / "disp_left.pfm"),
            )
        )
    return pairs


def score(predictions: list[np.ndarray], pairs, limit: float) -> dict[str, float]:
    """EPE and Bad-3 over valid pixels with gt < limit, averaged over images."""
    averager = MetricAverager(max_disp=limit)
    for prediction, (_, _, truth) in zip(predictions, pairs):
        averager.update(prediction, truth)
    mean = averager.mean()
    return {"epe": float(mean["epe"]), "bad3": float(mean["bad_3"])}


def latency_s(backend, height: int, width: int, repeats: int) -> float:
    """Median wall time of one forward at height×width on a random-texture pair."""
    rng = np.random.default_rng(0)
    left = rng.integers(0, 255, (height, width, 3), dtype=np.uint8)
    right = np.roll(left, -8, axis=1)
    backend.compute(left, right)  # warm-up (builds the fused inference copy)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        backend.compute(left, right)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", required=True, help="EMCStereo checkpoint (any layout stereo.load_model reads)")
    parser.add_argument("--scenes", type=int, default=4, help="held-out synthetic scenes")
    parser.add_argument("--scene-seed", type=int, default=900, help="first synthetic seed")
    parser.add_argument("--scene-size", default="640x360", help="synthetic scene size WxH")
    parser.add_argument("--size", default="384x1248", help="latency size HxW")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    width, height = (int(v) for v in args.scene_size.split("x"))
    lat_h, lat_w = (int(v) for v in args.size.split("x"))
    sets = {"synthetic": synthetic_pairs(args.scenes, args.scene_seed, width, height), "real": real_pairs()}
    print(
        f"CPU: {cpu_name()}; weights {args.weights}; {args.threads} threads; latency at {lat_h}×{lat_w}; "
        f"synthetic {args.scenes} scenes {width}×{height}; real {len(sets['real'])} pairs"
    )
    header = f"{'max_disp':>8} {'latency s':>9} {'×192':>6}"
    for name in sets:
        header += f" | {name} EPE<192 {'Bad3<192':>8} EPE<{WORKING_RANGE} Bad3<{WORKING_RANGE}"
    print(header)
    baseline = None
    rows: list[dict] = []
    for max_disp in RANGES:
        backend = make_backend("emcstereo", weights=args.weights, max_disp=max_disp)
        seconds = latency_s(backend, lat_h, lat_w, args.repeats)
        baseline = baseline or seconds
        row = f"{max_disp:>8} {seconds:>9.2f} {seconds / baseline:>6.2f}"
        rows.append({"max_disp": max_disp, "latency_s": seconds, "latency_vs_192": seconds / baseline})
        for name, pairs in sets.items():
            if not pairs:
                row += " |" + " " * 40 + "n/a"
                continue
            predictions = [backend.compute(left, right).disparity for left, right, _ in pairs]
            everything, working = score(predictions, pairs, 192), score(predictions, pairs, WORKING_RANGE)
            rows[-1][name] = {"below_192": everything, f"below_{WORKING_RANGE}": working}
            row += (
                f" | {everything['epe']:>13.3f} {everything['bad3']:>8.3f}"
                f" {working['epe']:>6.3f} {working['bad3']:>7.3f}"
            )
        print(row, flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        report = {"cpu": cpu_name(), "settings": vars(args) | {"json": str(args.json)}, "rows": rows}
        args.json.write_text(json.dumps(report, indent=2), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
