"""Inference latency and peak memory of the stereo backends on the CPU, with the machine's FLOP rate.

Every configuration runs in its own child process, so that each peak RSS is that configuration's
alone; a float32 matmul timed on the same number of threads, in the same run, is the baseline.
Prints one table and the full model's efficiency at 384×1248: model GFLOP / latency / matmul rate.
The `cores` column (CPU time / wall time) shows how much of the requested threads a run really got.
The table is headed by the CPU (`machine.py`); `--json FILE` also writes every configuration's result.

    .venv/bin/python benchmarks/inference.py                      # 256×512 and 384×1248, 1+3 runs
    .venv/bin/python benchmarks/inference.py --sizes 256x512 --repeats 1 --warmup 0   # quick look
    .venv/bin/python benchmarks/inference.py --sizes 384x1248 --backends emcstereo,plain,parity --max-disp 192,96,64

Runners: `emcstereo` (the backend, fast path), `plain` (the same model's plain eager fp32 forward),
`onnx` (ONNX Runtime), `parity` (max |fast − plain| on the real pairs), `sgbm`; baselines `matmul`
(torch `@`, MKL) and `matmul-dnn` (oneDNN). To benchmark something new, add a runner to RUNNERS
and configurations to `build_configs`.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from machine import cpu_name  # a script's own folder is on its import path

if TYPE_CHECKING:  # imported in the child processes only, so the parent starts without torch
    import torch

#: The full model's forward pass at 384×1248 (max_disp 192), in GFLOP, the figure the
#: efficiency line is defined with (torch's FlopCounterMode counts 1338.8 for the convolutions
#: and matmuls alone).
FULL_MODEL_GFLOP_384x1248 = 1350.6
EFFICIENCY_SIZE = (384, 1248)


@dataclass(frozen=True)
class BenchConfig:
    """One measurement: which runner, at what input size, on how many threads."""

    runner: str
    height: int
    width: int
    threads: int = 2
    max_disp: int = 192
    warmup: int = 1
    repeats: int = 3


@dataclass
class BenchResult:
    """What a child process reports for one configuration (times in seconds, memory in MiB)."""

    latencies_s: list[float]
    cpu_s: list[float]
    peak_rss_mib: float
    extra: dict[str, float] = field(default_factory=dict)


def random_pair(height: int, width: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A random-texture RGB uint8 pair `H×W×3`, the right view shifted by 8 px."""
    rng = np.random.default_rng(seed)
    scene = rng.integers(0, 256, (height, width + 8, 3), dtype=np.uint8)
    return np.ascontiguousarray(scene[:, 8:]), np.ascontiguousarray(scene[:, :width])


def _timed(call: Callable[[], object], config: BenchConfig) -> tuple[list[float], list[float]]:
    """Run `call` warm-up times untimed, then `repeats` times: (wall seconds, process CPU seconds) of each.

    CPU seconds over wall seconds is the number of cores the run really got; on a shared machine
    it falls below the thread count when other work competes.
    """
    for _ in range(config.warmup):
        call()
    latencies, cpu = [], []
    for _ in range(config.repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        call()
        latencies.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return latencies, cpu


def run_emcstereo(config: BenchConfig) -> BenchResult:
    """The full (EMA+MSF+Coord) model behind the emcstereo backend, fp32, random weights."""
    import torch

    from stereo.backends.emcstereo import EMCStereoBackend
    from stereo.model import EMCStereo

    torch.manual_seed(0)
    backend = EMCStereoBackend(EMCStereo(), max_disp=config.max_disp)
    left, right = random_pair(config.height, config.width)
    network_ms: list[float] = []

    def call() -> None:
        network_ms.append(backend.compute(left, right).timing_ms["network"])

    latencies, cpu = _timed(call, config)
    return BenchResult(latencies, cpu, 0.0, {"network_ms": statistics.median(network_ms[config.warmup :])})


def run_sgbm(config: BenchConfig) -> BenchResult:
    """OpenCV SGBM with the left-right check, as the sgbm backend runs it."""
    from stereo.backends.sgbm import SGBMBackend

    backend = SGBMBackend(max_disp=config.max_disp)
    left, right = random_pair(config.height, config.width)
    return BenchResult(*_timed(lambda: backend.compute(left, right), config), 0.0)


def run_matmul(config: BenchConfig) -> BenchResult:
    """A square float32 matmul of side `height`: the FLOP rate the threads reach (GFLOP/s)."""
    import torch

    n = config.height
    a, b = torch.randn(n, n), torch.randn(n, n)
    latencies, cpu = _timed(lambda: a @ b, config)
    return BenchResult(latencies, cpu, 0.0, {"gflops_per_s": 2 * n**3 / statistics.median(latencies) / 1e9})


def _network_inputs(config: BenchConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """The random pair as the emcstereo backend feeds it to the network: normalised, padded tensors."""
    import torch

    from stereo.backends.emcstereo import normalize_images
    from stereo.padding import compute_padding, pad_image

    left, right = random_pair(config.height, config.width)
    images = pad_image(
        normalize_images(np.stack([left, right]), torch.device("cpu")), compute_padding(config.height, config.width)
    )
    return images[:1], images[1:]


def run_emcstereo_plain(config: BenchConfig) -> BenchResult:
    """The same model's plain eager fp32 forward (`infer(fast=False)`), network only: the parity reference."""
    import torch

    from stereo.model import EMCStereo

    torch.manual_seed(0)
    model = EMCStereo().eval()
    left, right = _network_inputs(config)
    with torch.inference_mode():
        return BenchResult(*_timed(lambda: model.infer(left, right, config.max_disp, fast=False), config), 0.0)


def run_onnx(config: BenchConfig) -> BenchResult:
    """The same model exported to ONNX at this size and range, under ONNX Runtime (export time apart)."""
    import tempfile

    import torch

    from stereo.backends.onnx import OnnxBackend
    from stereo.export import export_onnx
    from stereo.model import EMCStereo
    from stereo.padding import compute_padding

    torch.manual_seed(0)
    padded = compute_padding(config.height, config.width).padded_shape
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        path = export_onnx(EMCStereo().eval(), f"{folder}/model.onnx", *padded, config.max_disp)
        export_s = time.perf_counter() - start
        backend = OnnxBackend(path, threads=config.threads)
    left, right = random_pair(config.height, config.width)
    return BenchResult(*_timed(lambda: backend.compute(left, right), config), 0.0, {"export_s": export_s})


#: Real pairs the parity runner compares the fast path on (../shared/data/stereo).
PARITY_PAIRS = (("middlebury2001_tsukuba", "imL.png", "imR.png"), ("middlebury2001_venus", "imL.png", "imR.png"))


def run_parity(config: BenchConfig) -> BenchResult:
    """Max |fast − plain eager fp32| disparity (px) of the seeded model on the real pairs, at the pairs' own sizes."""
    from pathlib import Path

    import torch

    from stereo.backends.emcstereo import normalize_images
    from stereo.io.images import read_rgb
    from stereo.model import EMCStereo
    from stereo.padding import compute_padding, pad_image

    torch.manual_seed(0)
    model = EMCStereo().eval()
    root = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "stereo"
    worst = 0.0
    latencies, cpu = [], []
    for folder, left_name, right_name in PARITY_PAIRS:
        pair = np.stack([read_rgb(root / folder / left_name), read_rgb(root / folder / right_name)])
        images = pad_image(normalize_images(pair, torch.device("cpu")), compute_padding(*pair.shape[1:3]))
        with torch.inference_mode():
            start, start_cpu = time.perf_counter(), time.process_time()
            fast, _ = model.infer(images[:1], images[1:], config.max_disp)
            latencies.append(time.perf_counter() - start)
            cpu.append(time.process_time() - start_cpu)
            plain, _ = model.infer(images[:1], images[1:], config.max_disp, fast=False)
        worst = max(worst, float((fast - plain).abs().max()))
    return BenchResult(latencies, cpu, 0.0, {"parity_px": worst})


def run_matmul_onednn(config: BenchConfig) -> BenchResult:
    """The same square float32 product through oneDNN (a 1×1 convolution, channels-last): GFLOP/s.

    PyTorch's `@` goes to MKL, which on AMD CPUs can stay far below the machine's rate; the
    efficiency line uses the faster of the two baselines, so it never flatters the model.
    """
    import torch
    import torch.nn.functional as F

    n = config.height
    x = torch.randn(1, n, 1, n).contiguous(memory_format=torch.channels_last)
    w = torch.randn(n, n, 1, 1)
    latencies, cpu = _timed(lambda: F.conv2d(x, w), config)
    return BenchResult(latencies, cpu, 0.0, {"gflops_per_s": 2 * n**3 / statistics.median(latencies) / 1e9})


RUNNERS: dict[str, Callable[[BenchConfig], BenchResult]] = {
    "emcstereo": run_emcstereo,
    "plain": run_emcstereo_plain,
    "onnx": run_onnx,
    "parity": run_parity,
    "sgbm": run_sgbm,
    "matmul": run_matmul,
    "matmul-dnn": run_matmul_onednn,
}
#: Runners that measure the machine, not a backend; they run once, before the backends.
BASELINES = ("matmul", "matmul-dnn")


def child_main(config_json: str) -> None:
    """In the child: set the thread counts, run one configuration, print its result as JSON."""
    import cv2
    import torch

    config = BenchConfig(**json.loads(config_json))
    torch.set_num_threads(config.threads)
    cv2.setNumThreads(config.threads)
    result = RUNNERS[config.runner](config)
    result.peak_rss_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB
    print(json.dumps(asdict(result)))


def measure(config: BenchConfig) -> BenchResult:
    """Run one configuration in a fresh Python process and parse its report."""
    completed = subprocess.run(
        [sys.executable, __file__, "--child", json.dumps(asdict(config))], capture_output=True, text=True, check=False
    )
    if completed.returncode != 0:
        raise RuntimeError(f"benchmark child for {config} failed:\n{completed.stderr[-2000:]}")
    return BenchResult(**json.loads(completed.stdout.strip().splitlines()[-1]))


def parse_size(text: str) -> tuple[int, int]:
    """'384x1248' → (384, 1248)."""
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"size {text!r} must look like HEIGHTxWIDTH, e.g. 384x1248") from exc
    if height <= 0 or width <= 0:
        raise argparse.ArgumentTypeError(f"size {text!r} must be positive")
    return height, width


def build_configs(args: argparse.Namespace) -> list[BenchConfig]:
    """The matmul baseline, then each backend at each size."""
    common = {"threads": args.threads, "warmup": args.warmup, "repeats": args.repeats}
    configs = [BenchConfig(runner, args.matmul_size, args.matmul_size, **common) for runner in BASELINES]
    for runner in args.backends:
        if runner == "parity":  # the real pairs have their own sizes
            configs.append(
                BenchConfig(runner, 0, 0, max_disp=args.max_disp[0], threads=args.threads, warmup=0, repeats=1)
            )
            continue
        for height, width in args.sizes:
            for max_disp in args.max_disp if runner != "sgbm" else args.max_disp[:1]:
                configs.append(BenchConfig(runner, height, width, max_disp=max_disp, **common))
    return configs


def format_row(config: BenchConfig, result: BenchResult) -> str:
    """One line of the table."""
    median_ms = statistics.median(result.latencies_s) * 1e3
    size = f"{config.height}^2" if config.runner in BASELINES else f"{config.height}x{config.width}"
    if config.runner == "parity":
        size = "real"
    network = f"{result.extra['network_ms']:10.1f}" if "network_ms" in result.extra else f"{'':>10}"
    cores = statistics.median(c / w for c, w in zip(result.cpu_s, result.latencies_s))
    work = f"{result.extra['gflops_per_s']:9.1f} GFLOP/s" if "gflops_per_s" in result.extra else ""
    if "parity_px" in result.extra:
        work = f"max |fast - plain| {result.extra['parity_px']:.2e} px"
    if "export_s" in result.extra:
        work = f"export {result.extra['export_s']:.0f} s"
    return (
        f"{config.runner:<10} {size:>9} {config.threads:>7} "
        f"{config.max_disp if config.runner not in BASELINES else '':>8} "
        f"{median_ms:10.1f} {min(result.latencies_s) * 1e3:9.1f} {network} {cores:6.2f} "
        f"{result.peak_rss_mib:9.0f}  {work}"
    )


def main(argv: list[str] | None = None) -> int:
    """Run every configuration, print the table and the efficiency line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes",
        type=lambda s: [parse_size(v) for v in s.split(",")],
        default=[(256, 512), (384, 1248)],
        help="comma-separated HEIGHTxWIDTH list (default 256x512,384x1248)",
    )
    parser.add_argument(
        "--backends", type=lambda s: s.split(","), default=["emcstereo", "sgbm"], help="comma-separated runners"
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--max-disp",
        type=lambda s: [int(v) for v in s.split(",")],
        default=[192],
        help="comma-separated disparity ranges for the network runners (default 192)",
    )
    parser.add_argument("--matmul-size", type=int, default=2048)
    parser.add_argument("--json", type=Path, help="also write every configuration's result here")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child_main(args.child)
        return 0
    unknown = [name for name in args.backends if name not in RUNNERS]
    if unknown or args.repeats < 1 or args.warmup < 0 or args.threads < 1:
        parser.error(f"need known runners {sorted(RUNNERS)} (got {unknown}), repeats ≥ 1, warmup ≥ 0, threads ≥ 1")

    print(f"CPU: {cpu_name()}")
    print(
        f"{'backend':<10} {'size':>9} {'threads':>7} {'max_disp':>8} {'median ms':>10} {'min ms':>9} "
        f"{'network ms':>10} {'cores':>6} {'peak MiB':>9}  rate"
    )
    results: dict[BenchConfig, BenchResult] = {}
    for config in build_configs(args):
        results[config] = measure(config)
        print(format_row(config, results[config]), flush=True)

    rate = max(r.extra["gflops_per_s"] for c, r in results.items() if c.runner in BASELINES)
    print()
    measured = [
        (c.runner, r)
        for c, r in results.items()
        if c.runner in ("emcstereo", "plain") and (c.height, c.width) == EFFICIENCY_SIZE and c.max_disp == 192
    ]
    efficiencies = {}
    for runner, result in measured:
        latency = statistics.median(result.latencies_s)
        efficiency = efficiencies[runner] = FULL_MODEL_GFLOP_384x1248 / latency / rate
        print(
            f"efficiency at 384x1248 ({runner}): {FULL_MODEL_GFLOP_384x1248} GFLOP / {latency:.2f} s / "
            f"{rate:.1f} GFLOP/s (faster matmul, {args.threads} threads) = {efficiency:.1%}"
        )
    if not measured:
        print("\nefficiency: needs emcstereo at 384x1248 with max_disp 192 among the configurations")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        report = {
            "cpu": cpu_name(),
            "results": [{"config": asdict(c), "result": asdict(r)} for c, r in results.items()],
            "baseline_gflops_per_s": rate,
            "efficiency_384x1248": efficiencies,
        }
        args.json.write_text(json.dumps(report, indent=2), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
