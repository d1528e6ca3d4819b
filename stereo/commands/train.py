"""`emcstereo train --config FILE`: train EMCStereo with a recipe from stereo/configs (torchrun-ready)."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable

from torch.utils.data import Dataset

from stereo.checkpoints import CheckpointError
from stereo.datasets import DatasetError
from stereo.export import ExportError
from stereo.io import StereoIOError
from stereo.training.config import ConfigError, ExperimentConfig, load_config
from stereo.training.distributed import context_from_env, shutdown
from stereo.training.run import run_training
from stereo.training.selfsup import SelfSupConfig
from stereo.training.trainer import TrainResult

#: Errors caused by what the user gave (config, data, weights); the commands print them without a traceback.
INPUT_ERRORS = (ConfigError, DatasetError, CheckpointError, StereoIOError, ExportError)


def run_reporting_input_errors(command: str, body: Callable[[], int]) -> int:
    """Run a command's body; an input error becomes one `emcstereo COMMAND: error: …` line and exit status 2."""
    try:
        return body()
    except INPUT_ERRORS as exc:
        print(f"emcstereo {command}: error: {exc}", file=sys.stderr)
        return 2


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags shared by `train` and `finetune`: config file, common overrides, resume, device."""
    parser.add_argument("--config", required=True, help="TOML recipe (see stereo/configs/)")
    parser.add_argument("--data-root", help="override data.root")
    parser.add_argument("--out", help="override train.out_dir (checkpoints, logs, curve)")
    parser.add_argument("--epochs", type=int, help="override train.epochs")
    parser.add_argument("--batch-size", type=int, help="override train.batch_size (per process)")
    parser.add_argument(
        "--max-steps", type=int, help="stop after this many optimiser steps (the schedule keeps its length)"
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help='override any config key, e.g. --set train.precision="bf16" (repeatable)',
    )
    parser.add_argument("--resume", help="training checkpoint to continue from, or 'auto' for OUT/last.pth if present")
    parser.add_argument("--device", default="auto", help="auto (CUDA LOCAL_RANK if available), cpu or cuda")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars (e.g. in batch jobs)")


def config_from_args(args: argparse.Namespace, extra: list[str] = ()) -> ExperimentConfig:
    """The config file with the flags' overrides applied."""
    overrides = list(extra)
    for flag, key in (("data_root", "data.root"), ("out", "train.out_dir")):
        if getattr(args, flag):
            overrides.append(f'{key}="{getattr(args, flag)}"')
    for flag, key in (("epochs", "train.epochs"), ("batch_size", "train.batch_size"), ("max_steps", "train.max_steps")):
        if getattr(args, flag) is not None:
            overrides.append(f"{key}={getattr(args, flag)}")
    return load_config(args.config, overrides + list(args.set))


def report(result: TrainResult) -> None:
    """One summary line on how the run ended."""
    state = "stopped early" if result.stopped_early else "interrupted (max steps)" if result.interrupted else "finished"
    print(
        f"{state}: {result.steps} steps, {result.epochs_completed} epochs, best val EPE "
        f"{result.best_epe:.4f} px at epoch {result.best_epoch}"
    )


def launch(
    args: argparse.Namespace,
    config: ExperimentConfig,
    *,
    selfsup: SelfSupConfig | None = None,
    train_set: Dataset | None = None,
) -> int:
    """Join torchrun's process group (if any), train, leave it, and report on the main process."""
    context = context_from_env(os.environ, device=args.device)
    try:
        result = run_training(
            config,
            context=context,
            resume=args.resume,
            show_progress=not args.no_progress,
            selfsup=selfsup,
            train_set=train_set,
        )
    finally:
        shutdown(context)
    if context.is_main:
        report(result)
    return 0


def _run(args: argparse.Namespace) -> int:
    return run_reporting_input_errors("train", lambda: launch(args, config_from_args(args)))


def register(sub: argparse._SubParsersAction) -> None:
    """Add `train` to the `emcstereo` command."""
    parser = sub.add_parser("train", help="train EMCStereo from a TOML recipe (single GPU/CPU or torchrun)")
    add_run_arguments(parser)
    parser.set_defaults(func=_run)
