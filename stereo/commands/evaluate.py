"""`emcstereo evaluate --dataset NAME --root DIR --weights W [--split test]`: the paper's metric table.

Splits: for VirtualTree-layout sets a split-file name or path (default `test`); for the open
datasets `val` / `train` of the seeded 90/10 split (default `val`) or `all`. Several `--split`
flags give several rows. Writes `metrics.json`, `metrics.txt` and the first `--vis` panels.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

import stereo
from stereo.commands.train import run_reporting_input_errors
from stereo.commands.weights import add_no_verify_flag
from stereo.datasets import SPLIT_FILE_DATASETS, DatasetError, StereoDataset, open_dataset
from stereo.datasets.splits import split_train_val
from stereo.evaluation import EvaluationResult, evaluate, format_table, write_reports
from stereo.training.config import DATASET_NAMES


def split_dataset(name: str, root: str, split: str, val_fraction: float = 0.1, seed: int = 0) -> StereoDataset:
    """The pairs of one split: a split file for VirtualTree-layout sets, else part of the 90/10 split."""
    if name in SPLIT_FILE_DATASETS:
        return open_dataset(name, root, None if split == "all" else split)
    full = open_dataset(name, root)
    if split == "all":
        return full
    if split not in ("train", "val"):
        raise DatasetError(f"--split {split!r}: {name} has no split files; use val, train or all")
    train_idx, val_idx = split_train_val(len(full), val_fraction, seed)
    return full.subset(val_idx if split == "val" else train_idx)


def _run(args: argparse.Namespace) -> int:
    return run_reporting_input_errors("evaluate", lambda: _evaluate(args))


def _evaluate(args: argparse.Namespace) -> int:
    """Score the weights on every requested split, write the reports and print the table."""
    device = torch.device(args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu"))
    model = stereo.load_model(args.weights, device=device, verify_sha256=args.verify_sha256)
    splits = args.split or (["test"] if args.dataset in SPLIT_FILE_DATASETS else ["val"])
    out_dir = Path(args.out)
    results: dict[str, EvaluationResult] = {}
    for split in splits:
        dataset = split_dataset(args.dataset, args.root, split, args.val_fraction, args.seed)
        vis_dir = out_dir / "vis" / Path(split).stem if args.vis > 0 else None
        results[Path(split).stem] = evaluate(
            model,
            dataset,
            device=device,
            max_disp=args.max_disp,
            limit=args.limit,
            precision=args.precision,
            vis_dir=vis_dir,
            vis_count=args.vis,
            progress=not args.no_progress,
        )
    write_reports(
        results,
        out_dir,
        extra={
            "dataset": args.dataset,
            "root": str(args.root),
            "weights": str(args.weights),
            "precision": args.precision,
            "max_disp": args.max_disp,
            "note": "per-image metrics averaged over images; AbsRel and δ on disparity",
        },
    )
    print(format_table(results), end="")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add `evaluate` to the `emcstereo` command."""
    parser = sub.add_parser(
        "evaluate", help="score weights on a dataset split (EPE, D1-all, Bad-1/3, RMSE, AbsRel, δ1)"
    )
    parser.add_argument("--dataset", required=True, choices=DATASET_NAMES)
    parser.add_argument("--root", required=True, help="dataset folder")
    parser.add_argument("--weights", required=True, help="checkpoint (ours, the authors' or PSMNet's)")
    add_no_verify_flag(parser)
    parser.add_argument("--split", action="append", help="split to score (repeatable); default test / val")
    parser.add_argument("--out", default="eval", help="output folder for metrics.json, metrics.txt, vis/")
    parser.add_argument("--vis", type=int, default=10, help="draw the first N pairs (0 = none)")
    parser.add_argument("--limit", type=int, default=0, help="score only the first N pairs (0 = all)")
    parser.add_argument("--max-disp", type=int, default=192, help="ground truth ≥ this is not scored")
    parser.add_argument("--precision", default="fp32", choices=("fp32", "fp16", "bf16"))
    parser.add_argument("--val-fraction", type=float, default=0.1, help="open datasets: held-out fraction")
    parser.add_argument("--seed", type=int, default=0, help="open datasets: split seed")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--no-progress", action="store_true")
    parser.set_defaults(func=_run)
