"""`branchrange train-segmenter --coco annotations.json --images DIR --out BUNDLE`: fine-tune the learned segmenter
on your labelled frames (the labelling → fine-tune → check → deploy loop; `branchrange.learning.finetune`).

Reads the COCO file with pycocotools (polygons or RLE; categories named branch and trunk, others left out),
each frame's disparity from `stereo/` beside the images (export-frames writes it), holds out a seeded share
of the frames, starts from the shipped model (or --start, a model or bundle), mixes synthetic scenes into
every batch, and writes the model bundle BUNDLE: load it with `--segmenter learned:BUNDLE` or
`[segmenter.learned] model = "BUNDLE"`. `--int8` adds its int8 copy (`precision = "int8"` runs it).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import fields
from pathlib import Path

#: options of the synthetic-scene training that a fine-tune does not take
_SYNTHETIC_ONLY = ("stage", "config", "calibrate_only", "no_calibrate")
#: options that only a fine-tune takes
FINETUNE_ONLY = ("images", "stereo", "start", "steps", "synthetic_share", "holdout_share", "seed")


def add_finetune_arguments(p: argparse.ArgumentParser) -> None:
    """The fine-tune's options of `train-segmenter`."""
    g = p.add_argument_group("fine-tune on your labels (with --coco)")
    g.add_argument(
        "--coco", type=Path, help="COCO instance-segmentation labels (export-frames' annotations.json, corrected)"
    )
    g.add_argument("--images", type=Path, help="folder of the labelled images (default: images/ beside --coco)")
    g.add_argument(
        "--stereo", type=Path, help="folder of the frames' disparity .npz (default: stereo/ beside --images)"
    )
    g.add_argument(
        "--start", type=Path, help="model (.onnx) or bundle folder to start from (default: the shipped model)"
    )
    g.add_argument("--steps", type=int, help="optimiser steps (default 1500: ~10 min on 2 cores)")
    g.add_argument("--synthetic-share", type=float, help="share of each batch from synthetic scenes (default 0.5)")
    g.add_argument(
        "--holdout-share", type=float, help="share of the frames held out to measure and calibrate (default 0.2)"
    )
    g.add_argument("--seed", type=int, help="seed of the split, crops and augmentation (default 0)")


def _refuse(message: str) -> int:
    """Print `message` as the command's error and return its exit status, 2."""
    print(f"branchrange train-segmenter: error: {message}", file=sys.stderr)
    return 2


def run_finetune(args: argparse.Namespace) -> int:
    """Fine-tune on --coco and write the bundle --out; 2 with a clear message for bad input."""
    from branchrange.commands.training_overrides import parsed_overrides
    from branchrange.core.segmentation.bundle import bundle_model
    from branchrange.core.segmentation.learned import SHIPPED_MODEL
    from branchrange.core.segmentation.onnx_model import OnnxSegmenterError
    from branchrange.learning.coco_labels import LabelsError, read_labelled_frames
    from branchrange.learning.finetune import FineTuneConfig, finetune_branchnet
    from stereo.cli import package_version

    given = [f"--{name.replace('_', '-')}" for name in _SYNTHETIC_ONLY if getattr(args, name)]
    if given:
        return _refuse(f"{', '.join(given)}: options of the synthetic training, not of a fine-tune (--coco)")
    names = {"steps": args.steps, "synthetic_share": args.synthetic_share, "holdout_share": args.holdout_share}
    settings = {k: v for k, v in {**names, "seed": args.seed, "threads": min(2, args.workers)}.items() if v is not None}
    images = args.images or args.coco.parent / "images"

    def log(line: str) -> None:
        print(line, flush=True)

    try:
        settings |= parsed_overrides({f.name for f in fields(FineTuneConfig)}, args.set)
        config = FineTuneConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in settings.items()})
        start = SHIPPED_MODEL if args.start is None else args.start
        start = bundle_model(start) if start.is_dir() else start
        frames = read_labelled_frames(args.coco, images, args.stereo, log=log)
        metrics = finetune_branchnet(
            config,
            frames,
            start,
            args.out,
            args.data,
            log=log,
            workers=args.workers,
            version=package_version(),
            int8=args.int8,
        )
    except (LabelsError, OnnxSegmenterError, ValueError, TypeError) as exc:
        return _refuse(str(exc))
    for when in ("before", "after"):
        held = metrics["heldout"][when]["trunk_band_40"]
        synthetic = metrics["synthetic_validation"][when]
        print(
            f"{when:>6}: held-out IoU branch {held['iou_branch']:.3f}, trunk {held['iou_trunk']:.3f}; cut points "
            f"{held['cut_points_per_frame']:.2f}/frame, on a labelled branch {_share(held['precision'])}, labelled "
            f"branches found {_share(held['recall'])}; synthetic IoU branch {synthetic['synthetic_iou_branch']:.3f}"
        )
    print(f"wrote the bundle {args.out} (use it with --segmenter learned:{args.out})")
    return 0


def _share(value: float | None) -> str:
    """A share as a percentage, '–' when undefined (nothing to count)."""
    return "–" if value is None else f"{100 * value:.1f} %"
