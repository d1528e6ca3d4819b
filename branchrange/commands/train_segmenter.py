"""`branchrange train-segmenter --out DIR`: train the learned segmenter (`BranchNet`) on CPU from synthetic scenes.

Renders the scenes it needs into --data first, in --workers processes (cached: a second run, or a resumed
one, renders nothing), trains, validates on scenes kept apart, measures how often its cut points are right
to calibrate their confidence (scenes 2861–3100, SGBM, per `branchrange.learning.calibration.CALIBRATION_SETTINGS`: at
640 px with and without the second look at the trunk band, and at 1280 px), and writes to --out:
branchnet.onnx (what `--segmenter learned` runs with `[segmenter.learned] model =
"DIR/branchnet.onnx"`), branchnet.json (config, seed, SHA-256, validation IoU, confidence
calibrations), metrics.csv, training_curve.png and branchnet.pt (the torch
weights). With --coco it fine-tunes the model on your labelled frames instead and writes a model bundle
(`branchrange.commands.finetune_segmenter`). --calibrate-only re-measures the calibration of the model already
in --out; --int8 also writes
branchnet_int8.onnx (+ .json), an int8 copy with its own calibration (`branchrange.learning.quantize`).

A run saves its whole state (model, optimiser, schedule, random generators, step) to --out's checkpoint.pt at
every validation; killed, the same command with --resume continues it to the weights it would have had.
`--set domain='"randomized"'` trains on the randomized domain, `'"mixed"'` on it and the generator's scenes alike
(`BranchNetTrainConfig.domain`).

Reproduce the shipped model exactly (three stages, each starting from the last's weights; the third adds
the full-resolution feature branch; the first two need no calibration, `--no-calibrate`; 103 min on 2 cores
from nothing cached, bit for bit the shipped files: `benchmarks/segmenter_recipe.py` runs and checks them):
    branchrange train-segmenter --out runs/branchnet-stage1 --stage 1 --no-calibrate \\
        --config branchrange/core/segmentation/weights/branchnet.json
    branchrange train-segmenter --out runs/branchnet-stage2 --stage 2 --no-calibrate \\
        --config branchrange/core/segmentation/weights/branchnet.json
    branchrange train-segmenter --out runs/branchnet --stage 3 \\
        --config branchrange/core/segmentation/weights/branchnet.json --int8
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import fields
from pathlib import Path

from branchrange.commands.finetune_segmenter import FINETUNE_ONLY, add_finetune_arguments, run_finetune
from branchrange.commands.training_overrides import parsed_overrides


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `train-segmenter` to the `branchrange` command."""
    p = subparsers.add_parser(
        "train-segmenter",
        help="train the learned branch segmenter on synthetic scenes, or fine-tune it on your labels (--coco; CPU)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--out", required=True, type=Path, help="output directory (model, metadata, curve; with --coco: the bundle)"
    )
    p.add_argument(
        "--data", type=Path, default=Path("out/segdata"), help="cache of rendered training scenes (default out/segdata)"
    )
    p.add_argument("--config", type=Path, help="a branchnet.json whose 'config' to train with (default: built-in)")
    p.add_argument(
        "--stage",
        type=int,
        help="train stage K of the --config file's 'stages' (the shipped model has 3, each from the last's weights)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one training setting, e.g. --set steps=200 (JSON values; repeatable; with --coco the "
        "fine-tune's settings, `FineTuneConfig`)",
    )
    p.add_argument(
        "--calibrate-only", action="store_true", help="only (re)calibrate the confidence of --out's branchnet.onnx"
    )
    p.add_argument(
        "--ood-only",
        action="store_true",
        help="only (re)measure the out-of-distribution reference of --out's branchnet.onnx (and of its int8 copy "
        "with --int8) on synthetic scenes 2861–3020, stored in its JSON under 'ood' "
        "(`branchrange.learning.ood_reference`; calibrating measures it too)",
    )
    p.add_argument(
        "--int8",
        action="store_true",
        help="also write branchnet_int8.onnx, a statically quantized copy (~1.4× faster on CPU), and calibrate it",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=usable_cores(),
        help="processes the training scenes are rendered in and the confidence calibration measures its scenes in "
        "(default: one per core it may use)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the run killed in --out from its last checkpoint (written at every validation), with the same "
        "settings: the weights end as an uninterrupted run's",
    )
    p.add_argument(
        "--no-calibrate",
        action="store_true",
        help="train only, no confidence calibration: for a stage whose model only starts the next (~6–10 min saved)",
    )
    add_finetune_arguments(p)
    p.set_defaults(func=run)


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, as a container's cpuset limits it), else all."""
    affinity = getattr(os, "sched_getaffinity", None)
    return len(affinity(0)) if affinity else os.cpu_count() or 1


def training_config(config_file: Path | None, overrides: list[str], stage: int | None = None):
    """`BranchNetTrainConfig` from a branchnet.json's 'config' (or its 'stages'[`stage` − 1]) and KEY=VALUE
    overrides; ValueError naming the key."""
    from branchrange.learning.training import BranchNetTrainConfig

    values: dict = {}
    if stage is not None and config_file is None:
        raise ValueError("--stage needs --config (a branchnet.json with 'stages')")
    if stage is not None and stage < 1:
        raise ValueError(f"--stage {stage}: stages count from 1")
    if config_file is not None:
        try:
            meta = json.loads(config_file.read_text(encoding="utf-8"))
            values = dict(meta["config"] if stage is None else meta["stages"][stage - 1])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"--config {config_file}: not a branchnet.json with a 'config' object ({exc})") from None
        except IndexError:
            raise ValueError(f"--stage {stage}: {config_file} has {len(meta['stages'])} stages") from None
    known = {f.name for f in fields(BranchNetTrainConfig)}
    values.update(parsed_overrides(known, overrides))
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown training setting(s) {unknown}; known: {', '.join(sorted(known))}")
    return BranchNetTrainConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


def run(args: argparse.Namespace) -> int:
    """Check the arguments, then train (unless --calibrate-only), calibrate and report the final validation IoU;
    a model file that cannot be run (`OnnxSegmenterError`) is an error message and exit 2, not a traceback."""
    from branchrange.core.segmentation.onnx_model import OnnxSegmenterError

    model = args.out / "branchnet.onnx"
    if args.workers < 1:
        return _refuse(f"--workers {args.workers}: at least 1")
    if args.coco is not None:
        return run_finetune(args)
    alone = [f"--{n.replace('_', '-')}" for n in FINETUNE_ONLY if getattr(args, n) is not None]
    if alone:
        return _refuse(f"{', '.join(alone)}: options of a fine-tune, which needs --coco (your labels)")
    if args.calibrate_only and args.no_calibrate:
        return _refuse("--calibrate-only and --no-calibrate exclude each other")
    if args.resume and (args.calibrate_only or args.ood_only):
        return _refuse("--resume continues a training run: it excludes --calibrate-only and --ood-only")
    if args.calibrate_only and not model.is_file():
        return _refuse(f"{model} does not exist (train first)")
    try:
        if args.ood_only:
            return _measure_ood(args, model)
        return _train_and_calibrate(args, model)
    except OnnxSegmenterError as exc:
        return _refuse(str(exc))


def _refuse(message: str) -> int:
    """Print `message` as the command's error and return its exit status, 2."""
    print(f"branchrange train-segmenter: error: {message}", file=sys.stderr)
    return 2


def _measure_ood(args: argparse.Namespace, model: Path) -> int:
    """--ood-only: measure the out-of-distribution reference of `model` (and its int8 copy with --int8) on the
    scenes cached in --data (`branchrange.learning.ood_reference.measure_model_reference`); exit 2 naming a model that
    is missing or a mode it excludes."""
    from branchrange.learning.ood_reference import measure_model_reference
    from branchrange.learning.quantize import int8_path

    if args.calibrate_only or args.no_calibrate:
        return _refuse("--ood-only excludes --calibrate-only and --no-calibrate")
    models = [model, *([int8_path(model)] if args.int8 else [])]
    missing = [path for path in models if not path.is_file()]
    if missing:
        return _refuse(f"{missing[0]} does not exist (train first)")
    for path in models:
        measure_model_reference(path, args.data / "calibration", log=lambda line: print(line, flush=True))
    return 0


def _train_and_calibrate(args: argparse.Namespace, model: Path) -> int:
    """`run` once the arguments are checked: train `model` (unless --calibrate-only), calibrate it (unless
    --no-calibrate) in --workers processes, and the int8 copy with --int8."""
    from branchrange.learning.calibration import calibrate_model
    from branchrange.learning.training import train_branchnet

    def log(line: str) -> None:
        print(line, flush=True)

    def calibrate(path: Path) -> None:
        calibrate_model(path, cache=args.data / "calibration", log=log, workers=args.workers)

    if args.calibrate_only:
        calibrate(model)
    else:
        try:
            config = training_config(args.config, args.set, args.stage)
            meta = train_branchnet(config, args.out, args.data, log=log, workers=args.workers, resume=args.resume)
        except (ValueError, TypeError) as exc:
            return _refuse(str(exc))
        if not args.no_calibrate:
            calibrate(model)
        final = meta["final"]
        print(
            f"wrote {model} (SHA-256 {meta['onnx_sha256'][:16]}…): validation IoU "
            f"branch {final['iou_branch']:.3f}, trunk {final['iou_trunk']:.3f}"
        )
    if args.int8:
        from branchrange.learning.quantize import int8_path, quantize_branchnet

        quantized = quantize_branchnet(model, args.data)
        if not args.no_calibrate:
            calibrate(int8_path(model))
        print(
            f"wrote {int8_path(model)} (SHA-256 {quantized['onnx_sha256'][:16]}…)"
            + ("" if args.no_calibrate else ", calibrated")
        )
    return 0
