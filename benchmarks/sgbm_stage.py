"""The SGBM stage against plain OpenCV SGBM, side by side in one run: time, each step's cost, accuracy.

Timing input: a synthetic ZED-Mini-like HD720 pair rendered with `stereo.synth.render_scene`
(1280×720, f = 640 px, B = 0.063 m; its own true disparity scores it too). For each max_disp (64,
128) it times, interleaved repeat by repeat so host load hits all alike (median reported):
- plain OpenCV `StereoSGBM` as shipped: 3-way, block 5, P1/P2 = 8/32·channels·25, colour; and on
  grey (the RGB → grey conversion included);
- this backend's steps: the grey matcher alone (block 3, uniqueness, speckle), + left padding,
  + the half-resolution left-right check (= `make_backend("sgbm")`), and its per-stage split;
- ratios against plain colour and plain grey of the same run.
Then the same for the coarse pass of the ROI mode (640×360, the HD720 pair resized, 64 px) and a
320×240 region with a 32-px window (`compute_roi`) against plain OpenCV on a 320×240 crop searching
32 disparities. Accuracy: EPE / Bad-1 / Bad-2 on matched pixels and density (matched share of
pixels with truth), on the real pairs of ../shared/data/stereo (Tsukuba and Venus at 32 px, the
SceneFlow frame at 192) and the synthetic HD720 pair (128), for plain OpenCV and each step.

OpenCV runs on `cv2.setNumThreads(THREADS)` = 2 threads, set explicitly (the onboard CPU budget;
OpenCV's default is all cores). The CPU is named from `lscpu` with its AVX2/AVX-512 flags, and the
1-minute load average before and after is printed: on a shared host compare ratios, not times.

    PYTHONPATH=. python benchmarks/sgbm_stage.py [--repeats 7] [--seed 3] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from machine import cpu_name  # a script's own folder is on its import path

from stereo.backends import SGBMBackend
from stereo.io import read_middlebury2001_disparity, read_middlebury2001_info, read_pfm, read_rgb
from stereo.metrics import image_metrics
from stereo.synth import SynthCamera, render_scene

THREADS = 2
SHARED_STEREO = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "stereo"
REAL_PAIRS = (
    ("middlebury2001_tsukuba", 32),
    ("middlebury2001_venus", 32),
    ("sceneflow_flyingthings3d_train_A_0000_0006", 192),
)
ROI_BOX = (480, 240, 800, 480)  # 320×240 at the HD720 frame's centre
ROI_WINDOW = 32

Method = Callable[[np.ndarray, np.ndarray], np.ndarray]


def plain_opencv(max_disp: int, grey: bool, min_disp: int = 0) -> Method:
    """OpenCV StereoSGBM as shipped (3-way, block 5); float32 px, 0 unmatched. Grey includes the conversion."""
    channels = 1 if grey else 3
    matcher = cv2.StereoSGBM_create(
        min_disp, max_disp, 5, P1=8 * channels * 25, P2=32 * channels * 25, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY
    )

    def run(left: np.ndarray, right: np.ndarray) -> np.ndarray:
        if grey:
            left, right = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY), cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
        disparity = matcher.compute(left, right).astype(np.float32) / 16.0
        return np.where(disparity > min_disp, disparity, 0.0).astype(np.float32)

    return run


def methods(max_disp: int) -> dict[str, Method]:
    """Plain OpenCV (colour, grey) and this backend step by step; the last is the backend as shipped."""
    steps = {
        "ours: matcher only": SGBMBackend(max_disp, pad_left=False, lr_check=False),
        "ours: + left padding": SGBMBackend(max_disp, lr_check=False),
        "ours: + half-res LR check (shipped)": SGBMBackend(max_disp),
    }
    return {
        "plain OpenCV colour": plain_opencv(max_disp, grey=False),
        "plain OpenCV grey": plain_opencv(max_disp, grey=True),
        **{name: (lambda left, right, b=backend: b.compute(left, right).disparity) for name, backend in steps.items()},
    }


def interleaved_medians(calls: dict[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    """Median wall-clock ms of each call, one warm-up each, then the calls taken in turn `repeats` times."""
    for call in calls.values():
        call()
    samples: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            samples[name].append((time.perf_counter() - start) * 1e3)
    return {name: statistics.median(values) for name, values in samples.items()}


def time_whole_frame(left: np.ndarray, right: np.ndarray, max_disp: int, repeats: int) -> dict[str, object]:
    """Per-method medians, the shipped backend's stage split, and ratios to plain OpenCV."""
    shipped = SGBMBackend(max_disp)
    stages: list[dict[str, float]] = []
    calls: dict[str, Callable[[], object]] = {
        name: (lambda m=method: m(left, right)) for name, method in methods(max_disp).items()
    }
    calls["ours: + half-res LR check (shipped)"] = lambda: stages.append(shipped.compute(left, right).timing_ms)
    medians = interleaved_medians(calls, repeats)
    ours = medians["ours: + half-res LR check (shipped)"]
    return {
        "size": f"{left.shape[1]}x{left.shape[0]}",
        "max_disp": max_disp,
        "ms": medians,
        "stages_ms": {key: statistics.median(s[key] for s in stages) for key in stages[0]},
        "ratio_to_plain_colour": ours / medians["plain OpenCV colour"],
        "ratio_to_plain_grey": ours / medians["plain OpenCV grey"],
    }


def time_roi(left: np.ndarray, right: np.ndarray, disparity: np.ndarray, repeats: int) -> dict[str, object]:
    """`compute_roi` on a 320×240 box with a 32-px window around its median true disparity, against
    plain OpenCV (colour, grey) on a 320×240 crop with 32 disparities."""
    x0, y0, x1, y1 = ROI_BOX
    truth = disparity[y0:y1, x0:x1]
    d_min = max(int(np.median(truth[truth > 0])) - ROI_WINDOW // 2, 0)
    backend = SGBMBackend(ROI_WINDOW)
    crop_left, crop_right = (np.ascontiguousarray(image[y0:y1, x0:x1]) for image in (left, right))
    colour, grey = plain_opencv(ROI_WINDOW, grey=False), plain_opencv(ROI_WINDOW, grey=True)
    medians = interleaved_medians(
        {
            "plain OpenCV colour (crop)": lambda: colour(crop_left, crop_right),
            "plain OpenCV grey (crop)": lambda: grey(crop_left, crop_right),
            "ours compute_roi": lambda: backend.compute_roi(left, right, ROI_BOX, d_min, ROI_WINDOW),
        },
        repeats,
    )
    result = backend.compute_roi(left, right, ROI_BOX, d_min, ROI_WINDOW).disparity
    return {
        "roi": ROI_BOX,
        "d_min": d_min,
        "d_range": ROI_WINDOW,
        "ms": medians,
        "ratio_to_plain_colour": medians["ours compute_roi"] / medians["plain OpenCV colour (crop)"],
        "ratio_to_plain_grey": medians["ours compute_roi"] / medians["plain OpenCV grey (crop)"],
        "accuracy": scores(result, truth),
    }


def scores(prediction: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """EPE, Bad-1, Bad-2 on matched pixels (prediction > 0) and density over pixels with truth (0 < gt < 192)."""
    matched = prediction > 0
    scored = (truth > 0) & (truth < 192)
    metrics = image_metrics(prediction, np.where(matched, truth, 0))
    return {
        "epe": metrics["epe"],
        "bad_1": metrics["bad_1"],
        "bad_2": metrics["bad_2"],
        "density": float(matched[scored].mean()),
    }


def real_pairs() -> list[tuple[str, int, np.ndarray, np.ndarray, np.ndarray]]:
    """(name, max_disp, left, right, true disparity) of the real pairs present in ../shared/data/stereo."""
    pairs = []
    for name, max_disp in REAL_PAIRS:
        folder = SHARED_STEREO / name
        if not folder.is_dir():
            continue
        if name.startswith("sceneflow"):
            pairs.append(
                (
                    name,
                    max_disp,
                    read_rgb(folder / "left_cleanpass.png"),
                    read_rgb(folder / "right_cleanpass.png"),
                    read_pfm(folder / "disp_left.pfm"),
                )
            )
        else:
            scale = read_middlebury2001_info(folder / "info.txt").scale
            pairs.append(
                (
                    name,
                    max_disp,
                    read_rgb(folder / "imL.png"),
                    read_rgb(folder / "imR.png"),
                    read_middlebury2001_disparity(folder / "groundtruth.png", scale),
                )
            )
    return pairs


def accuracy(
    pairs: list[tuple[str, int, np.ndarray, np.ndarray, np.ndarray]],
) -> dict[str, dict[str, dict[str, float]]]:
    """scores() of every method on every pair: {pair: {method: scores}}."""
    return {
        name: {method: scores(run(left, right), truth) for method, run in methods(max_disp).items()}
        for name, max_disp, left, right, truth in pairs
    }


def print_report(report: dict[str, object]) -> None:
    """The tables for people."""
    print(
        f"CPU: {report['cpu']}; OpenCV {report['opencv']} on {THREADS} threads; load average "
        f"{report['load_before']:.2f} → {report['load_after']:.2f}; {report['repeats']} repeats, median\n"
    )
    for run in report["whole_frame"]:
        print(f"### {run['size']}, max_disp {run['max_disp']}")
        print("| method | ms | × plain colour | × plain grey |\n|---|---|---|---|")
        colour, grey = run["ms"]["plain OpenCV colour"], run["ms"]["plain OpenCV grey"]
        for name, ms in run["ms"].items():
            print(f"| {name} | {ms:.1f} | {ms / colour:.2f} | {ms / grey:.2f} |")
        print("shipped stages (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in run["stages_ms"].items()) + "\n")
    roi = report["roi"]
    print(f"### ROI {roi['roi']} (320×240) on HD720, window [{roi['d_min']}, {roi['d_min'] + roi['d_range']})")
    print("| method | ms |\n|---|---|")
    for name, ms in roi["ms"].items():
        print(f"| {name} | {ms:.2f} |")
    print(
        f"compute_roi × plain colour {roi['ratio_to_plain_colour']:.2f}, "
        f"× plain grey {roi['ratio_to_plain_grey']:.2f}; "
        f"accuracy in the box: " + ", ".join(f"{k} {v:.3f}" for k, v in roi["accuracy"].items()) + "\n"
    )
    print("### Accuracy (matched-pixel EPE px / Bad-1 / Bad-2, density)")
    pairs = list(report["accuracy"])
    print("| method | " + " | ".join(pairs) + " |\n|---|" + "---|" * len(pairs))
    for method in report["accuracy"][pairs[0]]:
        cells = [report["accuracy"][p][method] for p in pairs]
        print(
            f"| {method} | "
            + " | ".join(f"{c['epe']:.3f} / {c['bad_1']:.3f} / {c['bad_2']:.3f}, {c['density']:.3f}" for c in cells)
            + " |"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7, help="timed runs per method (median reported)")
    parser.add_argument("--seed", type=int, default=3, help="synthetic scene seed")
    parser.add_argument("--json", type=Path, help="write the report as JSON here")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be ≥ 1, got {args.repeats}")
    cv2.setNumThreads(THREADS)
    load_before = os.getloadavg()[0]
    scene = render_scene(args.seed, SynthCamera.zed_mini(1280, 720))
    coarse_left, coarse_right = (
        cv2.resize(image, (640, 360), interpolation=cv2.INTER_AREA) for image in (scene.left, scene.right)
    )
    report: dict[str, object] = {
        "cpu": cpu_name(),
        "opencv": cv2.__version__,
        "threads": THREADS,
        "repeats": args.repeats,
        "seed": args.seed,
        "timing_input": "synthetic ZED Mini HD720 pair (stereo.synth.render_scene); 640x360 = it resized (INTER_AREA)",
        "whole_frame": [time_whole_frame(scene.left, scene.right, max_disp, args.repeats) for max_disp in (64, 128)]
        + [time_whole_frame(coarse_left, coarse_right, 64, args.repeats)],
        "roi": time_roi(scene.left, scene.right, scene.disparity, args.repeats),
    }
    pairs = real_pairs() + [("synthetic_hd720", 128, scene.left, scene.right, scene.disparity)]
    report["accuracy"] = accuracy(pairs)
    report["load_before"], report["load_after"] = load_before, os.getloadavg()[0]
    print_report(report)
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
