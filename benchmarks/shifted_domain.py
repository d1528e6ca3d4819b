"""A domain the shipped segmenter never saw: does its out-of-distribution signal say so, and how does it fare?

Scenes: held-out scenes of the training distribution ("park", seeds 50000+ as in `benchmarks/segmenter.py`) and
of the shifted domain (`SynthOptions(domain="orchard")`: espalier trees along trellis wires, a row behind, other
barks, leaves and light; seeds `SHIFTED_SEED`+), 640×360, SGBM, each through `Pipeline.process_disparity` as in
`benchmarks/segmenter.py` (recall within 5 cm, false cut points a frame with 95 % intervals over scenes; the
cut points at confidence ≥ 0.8 and the share of them within 5 cm, the issue's "≥ 0.8 → ≥ 90 % right"; the
actionable false cut points a frame, those more than 5 cm off at ≥ `cutpoints.target_min_confidence`'s
default; the expected calibration error).

Out-of-distribution signal (`branchrange.core.segmentation.ood`): per model (the shipped fp32 and int8), each
frame's statistic (hesitant background) read against the model's reference (its JSON's "ood", measured on
calibration scenes 2861–3020); the AUROC of it separating the shifted frames from the held-out park frames
(target ≥ 0.9), and the share of each flagged. Its cost: the statistic and reading per frame against the
network's first look, timed in the same run (ratio), on this machine (CPU and load printed).

`--ceiling` also scores the scenes' truth masks the same way: the recall SGBM leaves any segmenter.

Fine-tune proof (`--finetune 20,50,100`): for each N, N shifted-domain frames (seeds `FINETUNE_SEED`+, apart
from the held-out ones) are written as a COCO data set labelled with their truth (`offline.synth_coco`: the
labelling step, simulated), `branchrange train-segmenter --coco DIR/annotations.json --images DIR/images --out
BUNDLE` fine-tunes on them, and the bundle's model is scored like the shipped one on the held-out shifted and
park scenes: before/after with 95 % intervals, and whether the OOD flag clears on the shifted frames (against
the bundle's own reference; one measured here on its training frames when the bundle has none, said so).

    python benchmarks/shifted_domain.py [--scenes 60] [--shifted 60] [--cache out/shifted] [--json out.json]
                                        [--finetune 20,50,100 --work out/shifted/finetune]
                                        [--train-args "--synthetic-share 0.25" --tag _s25]
                                        [--shipped-from benchmarks/shifted_domain_finetune50.json]
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from machine import cpu_name  # a script's own folder is on its import path
from segmenter import FIRST_SEED, HD720, onboard_roi

from branchrange.core.confidence import cut_point_outcomes, expected_calibration_error, share_correct_above
from branchrange.core.cutpoints import CutPointConfig
from branchrange.core.frame_result import FrameResult
from branchrange.core.geometry import StereoGeometry
from branchrange.core.pipeline import Pipeline, untracked_whole_frame
from branchrange.core.segmentation.learned import SHIPPED_MODELS, LearnedSegmenter, LearnedSegmenterConfig
from branchrange.core.segmentation.ood import OodReference, frame_statistic, reference_in
from branchrange.learning.calibration import CALIBRATION_SEEDS
from branchrange.learning.ood_reference import first_look_statistic, model_reference
from branchrange.learning.samples import evaluation_scene
from branchrange.offline.evaluate_cuts import CutScores
from branchrange.offline.synth_coco import export_domain_frames

#: held-out scenes of the shifted domain start here (the park's held-out ones at `FIRST_SEED`)
SHIFTED_SEED = 80_000
#: the frames a fine-tune is given (labelled) start here, apart from every held-out seed
FINETUNE_SEED = 90_000
DOMAIN = "orchard"
#: the whole segmenter is timed this many times a frame with the signal on and off, alternated (`ood_cost_ms`)
REPEATS = 3


def auroc(negatives: Sequence[float], positives: Sequence[float]) -> float:
    """Area under the ROC curve of a score that should be higher on `positives`: the chance that a random
    positive scores above a random negative (ties count half)."""
    neg, pos = np.asarray(negatives, dtype=float), np.asarray(positives, dtype=float)
    if neg.size == 0 or pos.size == 0:
        return float("nan")
    greater = (pos[:, None] > neg[None, :]).mean()
    ties = (pos[:, None] == neg[None, :]).mean()
    return float(greater + 0.5 * ties)


def parse_counts(text: str) -> list[int]:
    """'20,50,100' → [20, 50, 100]; ValueError naming what is wrong (each a positive integer)."""
    try:
        counts = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise ValueError(f"--finetune {text!r}: expected frame counts like 20,50,100") from None
    if not counts or any(n < 1 for n in counts):
        raise ValueError(f"--finetune {text!r}: each count must be a positive integer")
    return counts


def scene_seeds(domain: str, count: int) -> range:
    """The held-out seeds of `domain` ("park" or the shifted one)."""
    return range(
        FIRST_SEED if domain == "park" else SHIFTED_SEED, (FIRST_SEED if domain == "park" else SHIFTED_SEED) + count
    )


def score_model(
    model: Path | None,
    seeds: Sequence[int],
    domain: str,
    cache: Path | None,
    reference: OodReference | None,
    roi_hd720: bool = False,
) -> dict:
    """Recall within 5 cm, false cut points a frame (95 % intervals), cut points at ≥ 0.8 and the share right,
    calibration error, and the OOD statistics (flagged against `reference`) of the ONNX `model` on scenes `seeds` of
    `domain`, SGBM, whole frame; `model` None: the scenes' truth masks (the ceiling SGBM leaves a segmenter). With
    `roi_hd720`, also "roi_hd720": the same scenes rendered at HD720 through the onboard roi mode as the vehicle
    flies (`benchmarks/segmenter.py`'s `onboard_roi`: the segmenter sees the 640×360 coarse pass, each branch is
    matched again at 1280×720) — where the issue's recall and calibration targets are judged."""
    segmenter = None if model is None else LearnedSegmenter(LearnedSegmenterConfig(model=str(model), ood=False))
    name = "truth" if model is None else model.name
    scores, outcomes, statistics = CutScores("sgbm", name), [], []
    flown = (CutScores("roi-hd720", name), []) if roi_hd720 else None
    for seed in seeds:
        scene = evaluation_scene(seed, cache, domain=domain)
        f, b, cx, cy = (float(v) for v in scene["camera"])
        pipeline = Pipeline(
            untracked_whole_frame(), focal_px=f, baseline_m=b, principal_point=(cx, cy), segmenter=segmenter
        )
        mask = scene["mask"] if segmenter is None else None
        result = pipeline.process_disparity(
            scene["left"], scene["sgbm"], scene["sgbm_conf"], mask=mask, backend="sgbm", right=scene["right"]
        )
        tally(scores, outcomes, scene["truth"], result)
        if reference is not None and segmenter is not None:
            statistics.append(first_look_statistic(segmenter, scene["left"], scene["sgbm"]))
        if flown is not None:
            wide = evaluation_scene(seed, cache, size=HD720, domain=domain)
            f, b, cx, cy = (float(v) for v in wide["camera"])
            roi = Pipeline(onboard_roi(), focal_px=f, baseline_m=b, principal_point=(cx, cy), segmenter=segmenter)
            tally(
                *flown,
                wide["truth"],
                roi.process(wide["left"], wide["right"], mask=None if segmenter else wide["mask"]),
            )
    return {
        "domain": domain,
        **summary(scores, outcomes, len(seeds)),
        "ood_statistics": [round(v, 4) for v in statistics],
        "ood_flagged": None
        if reference is None
        else float(np.mean([reference.reading(v).flagged for v in statistics])),
        **({"roi_hd720": {"domain": domain, **summary(*flown, len(seeds)), "ood_flagged": None}} if flown else {}),
    }


def tally(scores: CutScores, outcomes: list[tuple[float, bool]], truth: list[dict], result: FrameResult) -> None:
    """Add one frame's `result` against its `truth` cut points to `scores` and to the (confidence, within 5 cm)
    `outcomes`."""
    scores.add_frame(truth, result.branches, result.target)
    outcomes += cut_point_outcomes(
        [(x.confidence, x.cut_point_m) for x in result.branches], [t["cut_point_m"] for t in truth]
    )


def summary(scores: CutScores, outcomes: list[tuple[float, bool]], scenes: int) -> dict:
    """The figures of `score_model` from one way of seeing the scenes: recall and false cut points with 95 %
    intervals, actionable false ones (more than 5 cm off at ≥ the default target confidence), ≥ 0.8 and the
    share right, the expected calibration error."""
    interval = scores.interval()
    count, share = share_correct_above(outcomes, 0.8)
    actionable = CutPointConfig().target_min_confidence
    return {
        "scenes": scenes,
        "recall": scores.recall,
        "recall_ci95": interval["recall"],
        "false_per_frame": scores.false_per_frame,
        "false_per_frame_ci95": interval["false_per_frame"],
        "actionable_false_per_frame": sum(c >= actionable and not ok for c, ok in outcomes) / scenes,
        "actionable_at": actionable,
        "at_0.8": count,
        "share_right_at_0.8": share,
        "calibration_error": expected_calibration_error(outcomes),
    }


def ood_cost_ms(model: Path, cache: Path | None, seeds: Sequence[int]) -> dict:
    """Median ms per frame, same run, frames interleaved: the network's first look, the OOD statistic + reading on
    it, and the whole segmenter (`segment`, default settings) with the signal on and off, each the least of
    `REPEATS` alternated runs — the shipped path's cost of the signal (median of on / off per frame, − 1)."""
    segmenter = LearnedSegmenter(LearnedSegmenterConfig(model=str(model)))
    without = LearnedSegmenter(LearnedSegmenterConfig(model=str(model), ood=False))
    assert segmenter.ood_reference is not None, "the shipped models carry a reference"
    times: dict[str, list[float]] = {"look": [], "ood": [], "on": [], "off": []}
    for seed in seeds:
        scene = evaluation_scene(seed, cache)
        f, b, cx, cy = (float(v) for v in scene["camera"])
        geometry = StereoGeometry(f, b, cx, cy)
        disparity = np.asarray(scene["sgbm"], dtype=np.float32)
        t = time.perf_counter()
        logits = segmenter.first_look(scene["left"], disparity)
        t1 = time.perf_counter()
        segmenter.ood_reference.reading(frame_statistic(logits))
        t2 = time.perf_counter()
        times["look"].append(1000 * (t1 - t))
        times["ood"].append(1000 * (t2 - t1))
        best = {"on": np.inf, "off": np.inf}
        for _ in range(REPEATS):  # alternated, the least of each: other processes' load only ever adds time
            for key, which in (("on", segmenter), ("off", without)):
                t = time.perf_counter()
                which.segment(scene["left"], disparity, geometry)
                best[key] = min(best[key], 1000 * (time.perf_counter() - t))
        for key, ms in best.items():
            times[key].append(ms)
    median = {key: float(np.median(values)) for key, values in times.items()}
    median["ratio"] = float(np.median(np.divide(times["on"], times["off"])))
    return {
        "first_look_ms": median["look"],
        "ood_ms": median["ood"],
        "ratio": median["ood"] / median["look"],
        "segment_on_ms": median["on"],
        "segment_off_ms": median["off"],
        "segment_ratio": median["ratio"],
    }


def bundle_model(bundle: Path) -> Path:
    """The ONNX model of a bundle written by `branchrange train-segmenter --coco`: the bundle itself when it is a
    file, else its one .onnx file of fp32 (names with "int8" skipped); FileNotFoundError when none."""
    if bundle.is_file():
        return bundle
    found = sorted(p for p in bundle.glob("*.onnx") if "int8" not in p.name)
    if not found:
        raise FileNotFoundError(f"{bundle}: no ONNX model in the bundle")
    return found[0]


def finetune(count: int, work: Path, cache: Path | None, extra: Sequence[str] = (), tag: str = "") -> tuple[Path, str]:
    """Export `count` labelled shifted-domain frames and fine-tune on them with the CLI (`extra`: more of its
    options, e.g. a synthetic share; the bundle folder named with `tag`); the bundle's model path and the
    command's output."""
    data = work / f"coco_{count}"
    annotations = export_domain_frames(data, range(FINETUNE_SEED, FINETUNE_SEED + count), DOMAIN, cache)
    bundle = work / f"bundle_{count}{tag}"
    command = [
        sys.executable, "-m", "branchrange.cli", "train-segmenter",
        "--coco", str(annotations), "--images", str(data / "images"), "--out", str(bundle), *extra,
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    return bundle_model(bundle), done.stdout


def bundle_reference(model: Path, count: int, cache: Path | None) -> tuple[OodReference, str]:
    """The bundle's own OOD reference from its JSON, or — when it has none — one measured on what it trained on
    (the park's calibration scenes and its `count` labelled frames, interleaved), and where it came from."""
    meta_path = model.with_suffix(".json")
    meta = json.loads(meta_path.read_text(encoding="utf-8")) if meta_path.is_file() else {}
    found = reference_in(meta)
    if found is not None:
        return found, "the bundle's own"
    park = [evaluation_scene(s, cache) for s in range(*CALIBRATION_SEEDS)][: 2 * count]
    shifted = [evaluation_scene(s, cache, domain=DOMAIN) for s in range(FINETUNE_SEED, FINETUNE_SEED + count)]
    mixed = [scene for pair in zip(park[::2], park[1::2], shifted) for scene in pair]
    return model_reference(
        model, ((s["left"], s["sgbm"]) for s in mixed), f"park + {count} {DOMAIN} frames"
    ), "measured here"


def print_row(name: str, s: dict) -> None:
    """One line of the scores table."""
    lo, hi = s["recall_ci95"]
    flo, fhi = s["false_per_frame_ci95"]
    flagged = "—" if s["ood_flagged"] is None else f"{100 * s['ood_flagged']:.0f} %"
    print(
        f"{name:<34} {s['domain']:<8} {s['scenes']:>4} {100 * s['recall']:5.1f} [{100 * lo:4.1f}, {100 * hi:4.1f}]"
        f" {s['false_per_frame']:5.2f} [{flo:4.2f}, {fhi:4.2f}] {s.get('actionable_false_per_frame', math.nan):5.2f}"
        f" {s['at_0.8']:>5} {100 * s['share_right_at_0.8']:6.1f}"
        f" {s['calibration_error']:6.3f} {flagged:>8}"
    )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=60, help="held-out park scenes (default 60)")
    parser.add_argument("--shifted", type=int, default=60, help="held-out shifted-domain scenes (default 60)")
    parser.add_argument("--cache", type=Path, default=Path("out/shifted"), help="rendered scenes (default out/shifted)")
    parser.add_argument("--json", type=Path, help="write the results here")
    parser.add_argument(
        "--finetune", help="frame counts to fine-tune on, e.g. 20,50,100 (needs train-segmenter --coco)"
    )
    parser.add_argument("--work", type=Path, default=Path("out/shifted/finetune"), help="exported sets and bundles")
    parser.add_argument(
        "--train-args",
        default="",
        help='more train-segmenter options for --finetune, e.g. "--synthetic-share 0.25 --set lr=0.001" (a lever)',
    )
    parser.add_argument(
        "--ceiling", action="store_true", help="also score the scenes' truth masks: what SGBM leaves any segmenter"
    )
    parser.add_argument(
        "--roi-hd720",
        action="store_true",
        help="also score the shifted-domain scenes at HD720 through the onboard roi mode (the issue's targets)",
    )
    parser.add_argument("--tag", default="", help="a name for this lever: the bundle folder and the JSON key")
    parser.add_argument(
        "--shipped-from",
        type=Path,
        help="take the shipped models' figures from an earlier run's --json (same scenes) instead of scoring again",
    )
    parser.add_argument(
        "--export",
        type=int,
        metavar="N",
        help="only write N labelled shifted-domain frames as a COCO data set to WORK/coco_N (the labelling step)",
    )
    args = parser.parse_args(argv)
    if args.export is not None:
        if args.export < 1:
            parser.error(f"--export {args.export}: at least 1 frame")
        written = export_domain_frames(
            args.work / f"coco_{args.export}", range(FINETUNE_SEED, FINETUNE_SEED + args.export), DOMAIN, args.cache
        )
        print(f"wrote {written} ({args.export} {DOMAIN} frames labelled with their truth)")
        return 0
    try:
        counts = parse_counts(args.finetune) if args.finetune else []
    except ValueError as exc:
        parser.error(str(exc))
    if args.scenes < 2 or args.shifted < 2:
        parser.error("--scenes and --shifted need at least 2 scenes each")
    uptime = Path("/proc/loadavg").read_text().split()[:3] if Path("/proc/loadavg").is_file() else []
    print(f"CPU: {cpu_name()}; load average {' '.join(uptime)}")
    out: dict = {"cpu": cpu_name(), "load": uptime, "models": {}, "finetune": {}}
    header = (
        f"{'model':<34} {'domain':<8} {'n':>4} {'recall % [95 %]':<19} {'false/frame [95 %]':<19}"
        f" {'act.':>5} {'≥0.8':>5} {'right %':>6} {'ECE':>6} {'flagged':>8}"
    )
    if args.shipped_from is not None:
        out["models"] = json.loads(args.shipped_from.read_text(encoding="utf-8"))["models"]
        out["shipped_from"] = str(args.shipped_from)
    for precision, model in SHIPPED_MODELS.items() if args.shipped_from is None else ():
        reference = reference_in(json.loads(model.with_suffix(".json").read_text(encoding="utf-8")))
        park = score_model(model, scene_seeds("park", args.scenes), "park", args.cache, reference)
        shifted = score_model(model, scene_seeds(DOMAIN, args.shifted), DOMAIN, args.cache, reference)
        area = auroc(park["ood_statistics"], shifted["ood_statistics"])
        out["models"][precision] = {
            "park": park,
            DOMAIN: shifted,
            "auroc": area,
            "cost": ood_cost_ms(model, args.cache, scene_seeds("park", 10)),
        }
        print(header)
        print_row(f"shipped {precision}", park)
        print_row(f"shipped {precision}", shifted)
        cost = out["models"][precision]["cost"]
        print(
            f"  OOD AUROC park vs {DOMAIN}: {area:.3f} (target ≥ 0.9); cost {cost['ood_ms']:.2f} ms a frame against "
            f"{cost['first_look_ms']:.1f} ms for the network's first look ({100 * cost['ratio']:.1f} %); the whole "
            f"segmenter {cost['segment_on_ms']:.1f} ms with it, {cost['segment_off_ms']:.1f} ms without "
            f"({100 * (cost['segment_ratio'] - 1):+.1f} %)\n"
        )
    if args.ceiling:
        out["truth_masks"] = {
            d: score_model(None, scene_seeds(d, n), d, args.cache, None, roi_hd720=args.roi_hd720 and d == DOMAIN)
            for d, n in (("park", args.scenes), (DOMAIN, args.shifted))
        }
        print(header)
        for scores in out["truth_masks"].values():
            print_row("truth masks (the ceiling)", scores)
        if args.roi_hd720:
            print_row("truth masks, roi HD720", out["truth_masks"][DOMAIN]["roi_hd720"])
        print()
    shipped = out["models"]["fp32"]
    if args.roi_hd720 and "roi_hd720" not in shipped[DOMAIN]:
        seeds = scene_seeds(DOMAIN, args.shifted)
        shipped[DOMAIN]["roi_hd720"] = score_model(SHIPPED_MODELS["fp32"], seeds, DOMAIN, args.cache, None, True)[
            "roi_hd720"
        ]
    for count in counts:
        model, log = finetune(count, args.work, args.cache, shlex.split(args.train_args), args.tag)
        reference, origin = bundle_reference(model, count, args.cache)
        park = score_model(model, scene_seeds("park", args.scenes), "park", args.cache, reference)
        shifted = score_model(model, scene_seeds(DOMAIN, args.shifted), DOMAIN, args.cache, reference, args.roi_hd720)
        out["finetune"][f"{count}{args.tag}"] = {
            "park": park,
            DOMAIN: shifted,
            "reference": origin,
            "train_args": args.train_args,
            "train_log": log[-4000:],
        }
        print(header)
        print_row("shipped fp32 (before)", shipped[DOMAIN])
        print_row(f"fine-tuned on {count} ({origin} reference)", shifted)
        print_row("shipped fp32 (before)", shipped["park"])
        print_row(f"fine-tuned on {count}", park)
        if args.roi_hd720:
            print_row("shipped fp32, roi HD720", shipped[DOMAIN]["roi_hd720"])
            print_row(f"fine-tuned on {count}, roi HD720", shifted["roi_hd720"])
        print(f"  park recall after − before: {100 * (park['recall'] - shipped['park']['recall']):+.1f} points\n")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
