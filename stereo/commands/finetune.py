"""`emcstereo finetune --weights W --config FILE`: warm-started training, supervised or self-supervised.

`--weights` takes our, the authors' or PSMNet's checkpoints. `--freeze backbone` keeps the feature
extractor fixed. `--unlabelled DIR` switches to self-supervised fine-tuning on rectified pairs in
DIR/left and DIR/right (photometric + smoothness + left-right consistency); the config's dataset,
if it has ground truth, is then used only for validation.
"""

from __future__ import annotations

import argparse

from stereo.commands.train import add_run_arguments, config_from_args, launch, run_reporting_input_errors
from stereo.datasets import RectifiedPairsDataset
from stereo.training.selfsup import SelfSupConfig


def _run(args: argparse.Namespace) -> int:
    return run_reporting_input_errors("finetune", lambda: _finetune(args))


def _finetune(args: argparse.Namespace) -> int:
    """Warm-started training from the flags: supervised, or self-supervised with `--unlabelled`."""
    extra = [f'finetune.weights="{args.weights}"']
    if args.freeze:
        extra.append("finetune.freeze=[" + ", ".join(f'"{name}"' for name in args.freeze) + "]")
    config = config_from_args(args, extra)
    if not args.unlabelled:
        return launch(args, config)
    selfsup = SelfSupConfig(smoothness_weight=args.smoothness, lr_check=not args.no_lr_check)
    return launch(args, config, selfsup=selfsup, train_set=RectifiedPairsDataset(args.unlabelled))


def register(sub: argparse._SubParsersAction) -> None:
    """Add `finetune` to the `emcstereo` command."""
    parser = sub.add_parser(
        "finetune", help="fine-tune from our / the authors' / PSMNet weights, optionally self-supervised"
    )
    add_run_arguments(parser)
    parser.add_argument("--weights", required=True, help="checkpoint to start from (any supported layout)")
    parser.add_argument(
        "--freeze",
        action="append",
        default=[],
        metavar="MODULE",
        help="module to keep fixed, e.g. backbone (repeatable)",
    )
    parser.add_argument("--unlabelled", metavar="DIR", help="self-supervised on DIR/left/*.png + DIR/right/*.png")
    parser.add_argument("--smoothness", type=float, default=0.1, help="edge-aware smoothness weight (self-supervised)")
    parser.add_argument("--no-lr-check", action="store_true", help="do not mask left-right inconsistent pixels")
    parser.set_defaults(func=_run)
