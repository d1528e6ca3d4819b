"""What BranchNet's extra capacity costs: the network's time per frame at 640×360 with `deep_blocks` 0, 1, 2 …
against the shipped model, fp32 and int8, all timed in one run (issue 47's budget: the int8 network at most 1.2×
today's).

Each variant is `BranchNet(width, fine_width, deep_blocks)` of the shipped width with seeded random weights and
random batch-norm statistics (time does not depend on the values), exported as the training exports
(`branchrange.learning.training.export_onnx`) and quantized as the training quantizes
(`branchrange.learning.quantize.quantize_branchnet`, activation ranges from `--calibration-scenes` rendered
generator scenes). Every model runs in the session the segmenter opens (`onnx_model.onnx_session`, `--threads`
threads) on the network input of one rendered 640×360 frame (padded to 640×368): `--repeats` runs after two
warm-up runs, median and p90 in ms. Only the network is timed: the segmenter's instance step around it does not
change with the encoder, so the whole frame's ratio is smaller than the one printed.

    .venv/bin/python benchmarks/branchnet_capacity.py --deep-blocks 0 1 2 --json out/branchnet_capacity.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from machine import cpu_name  # a script's own folder is on its import path

from branchrange.core.segmentation.learned import SHIPPED_MODEL
from branchrange.core.segmentation.network_input import network_input, padded_to_stride
from branchrange.core.segmentation.onnx_model import onnx_session
from branchrange.learning.branchnet import BranchNet
from branchrange.learning.quantize import int8_path, quantize_branchnet
from branchrange.learning.samples import cached_sample
from branchrange.learning.training import export_onnx
from stereo.weights import sha256_of

#: generator scenes whose frames set the int8 copies' activation ranges (outside training and calibration seeds)
CALIBRATION_SCENES = (3301, 3305)
#: the frame every model is timed on
TIMED_SCENE = 3310


def random_network(width: int, fine_width: int, deep_blocks: int, seed: int = 0) -> BranchNet:
    """A `BranchNet` of seeded random weights and batch-norm statistics, in eval mode."""
    torch.manual_seed(seed)
    model = BranchNet(width, fine_width, deep_blocks)
    with torch.no_grad():
        for norm in (m for m in model.modules() if isinstance(m, torch.nn.BatchNorm2d)):
            assert norm.running_mean is not None and norm.running_var is not None
            norm.running_mean.normal_(0.0, 0.1)
            norm.running_var.uniform_(0.5, 1.5)
            norm.weight.uniform_(0.5, 1.5)  # a trained scale (a fresh residual block's is zero)
    return model.eval()


def exported(model: BranchNet, path: Path, calibration: list[dict[str, np.ndarray]]) -> tuple[Path, Path]:
    """`model` as the training writes it (ONNX and its JSON) and its int8 copy: (fp32 path, int8 path)."""
    export_onnx(model, path)
    meta = {"model": "BranchNet", "width": model.width, "fine_width": model.fine_width, "onnx_sha256": sha256_of(path)}
    path.with_suffix(".json").write_text(json.dumps(meta), encoding="utf-8")
    quantize_branchnet(path, path.parent, samples=calibration, samples_from="benchmark frames")
    return path, int8_path(path)


def time_model(path: Path, feed: np.ndarray, threads: int, repeats: int) -> dict[str, float]:
    """Median and p90 ms of `repeats` runs of the ONNX model `path` on `feed` (after two warm-up runs)."""
    session = onnx_session(path, threads=threads)
    name = session.get_inputs()[0].name
    for _ in range(2):
        session.run(None, {name: feed})
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        session.run(None, {name: feed})
        times.append((time.perf_counter() - start) * 1000)
    times.sort()
    return {"median_ms": statistics.median(times), "p90_ms": times[int(0.9 * (len(times) - 1))]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--deep-blocks", type=int, nargs="+", default=[0, 1, 2], help="variants (default 0 1 2)")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads (default 2, the segmenter's)")
    parser.add_argument("--repeats", type=int, default=30, help="timed runs per model (default 30)")
    parser.add_argument("--data", type=Path, default=Path("out/bench/branchnet_data"), help="rendered scenes cache")
    parser.add_argument("--json", type=Path, help="write the table here")
    args = parser.parse_args(argv)
    if any(not 0 <= d <= 4 for d in args.deep_blocks) or args.repeats < 1 or args.threads < 1:
        print("--deep-blocks must lie in 0..4, --repeats and --threads ≥ 1", file=sys.stderr)
        return 2
    shipped_meta = json.loads(SHIPPED_MODEL.with_suffix(".json").read_text(encoding="utf-8"))
    width, fine_width = int(shipped_meta["width"]), int(shipped_meta["fine_width"])
    calibration = [cached_sample(args.data, seed) for seed in range(*CALIBRATION_SCENES)]
    frame = cached_sample(args.data, TIMED_SCENE)
    feed = padded_to_stride(network_input(frame["left"], frame["disparity"]))[0][None]
    rows = {
        "shipped": {
            "parameters": None,
            "fp32": time_model(SHIPPED_MODEL, feed, args.threads, args.repeats),
            "int8": time_model(int8_path(SHIPPED_MODEL), feed, args.threads, args.repeats),
        }
    }
    with tempfile.TemporaryDirectory() as folder:
        for blocks in args.deep_blocks:
            model = random_network(width, fine_width, blocks)
            fp32, int8 = exported(model, Path(folder) / f"deep{blocks}.onnx", calibration)
            rows[f"deep_blocks={blocks}"] = {
                "parameters": sum(p.numel() for p in model.parameters()),
                "fp32": time_model(fp32, feed, args.threads, args.repeats),
                "int8": time_model(int8, feed, args.threads, args.repeats),
            }
    baseline = rows["shipped"]["int8"]["median_ms"]
    for row in rows.values():
        row["int8_ratio_to_shipped"] = row["int8"]["median_ms"] / baseline
    cpu = cpu_name()
    print(f"BranchNet at 640×368, {args.threads} threads, {args.repeats} runs each — {cpu}")
    print(f"{'model':<16} {'parameters':>10} {'fp32 ms':>9} {'int8 ms':>9} {'int8 p90':>9} {'int8 / shipped':>15}")
    for name, row in rows.items():
        parameters = "" if row["parameters"] is None else f"{row['parameters']:,}"
        print(
            f"{name:<16} {parameters:>10} {row['fp32']['median_ms']:>9.1f} {row['int8']['median_ms']:>9.1f} "
            f"{row['int8']['p90_ms']:>9.1f} {row['int8_ratio_to_shipped']:>14.2f}×"
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        report = {"cpu": cpu, "threads": args.threads, "repeats": args.repeats, "size": [640, 368], "models": rows}
        args.json.write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
