"""Smoke training of EMCStereo on `emcstereo synth` scenes, then optional self-supervised fine-tuning.

Renders a synthetic set, scores the untrained model on held-out scenes, trains with the real
Trainer for `--steps` steps, scores again, and (with `--selfsup-steps`) fine-tunes the trained
model self-supervised on the held-out pairs with their ground truth withheld, scoring once more.
Prints one table row per stage with held-out EPE / D1 / Bad-3 and seconds per iteration, under the CPU
(`machine.py`); `--json` also writes them.

    python benchmarks/train_synthetic.py --steps 100 --selfsup-steps 50 --threads 1 [--json F]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from machine import cpu_name  # a script's own folder is on its import path

from stereo import EMCStereo
from stereo.datasets import SyntheticDataset
from stereo.evaluation import evaluate
from stereo.synth.writer import split_line, write_dataset
from stereo.training.config import ExperimentConfig, build_config
from stereo.training.distributed import DistributedContext
from stereo.training.selfsup import SelfSupConfig, SelfSupervisedTrainer
from stereo.training.trainer import Trainer, seed_everything


class WithoutGroundTruth:
    """A dataset view whose samples carry no disparity (self-supervision must not see it)."""

    def __init__(self, dataset: SyntheticDataset) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int) -> dict:
        sample = self.dataset[index]
        return {**sample, "disparity": sample["disparity"] * 0}


def recipe(root: Path, out: Path, args: argparse.Namespace, steps: int, lr: float, pairs: int) -> ExperimentConfig:
    """The config of one stage: `steps` steps over whole epochs of `pairs` training pairs."""
    epochs = -(-steps // max(1, pairs // args.batch_size))
    return build_config(
        {
            "model": {"max_disp": args.max_disp},
            "data": {"dataset": "synthetic", "root": str(root), "crop": list(args.crop), "num_workers": 0},
            "optim": {"lr": lr, "warmup_steps": max(1, steps // 20)},
            "train": {
                "epochs": epochs,
                "batch_size": args.batch_size,
                "precision": args.precision,
                "patience": 0,
                "vis_count": 0,
                "max_steps": steps,
                "out_dir": str(out),
            },
        }
    )


def row(stage: str, metrics: dict, seconds_per_step: float | None) -> str:
    """One table line: stage, held-out EPE / D1 / Bad-3 and seconds per iteration."""
    spi = f"{seconds_per_step:8.3f}" if seconds_per_step is not None else f"{'-':>8}"
    return f"{stage:<28}{metrics['epe']:>8.3f}{metrics['d1_all']:>8.3f}{metrics['bad_3']:>8.3f}{spi}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("/tmp/emcstereo_synthetic_bench"))
    parser.add_argument("--train-scenes", type=int, default=8)
    parser.add_argument("--heldout-scenes", type=int, default=4)
    parser.add_argument("--size", type=int, nargs=2, default=(320, 256), metavar=("W", "H"))
    parser.add_argument("--crop", type=int, nargs=2, default=(256, 256), metavar=("H", "W"))
    parser.add_argument("--max-disp", type=int, default=48)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--selfsup-steps", type=int, default=0)
    parser.add_argument("--batch-size", type=int, default=1)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--precision", default="fp32")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = torch's default)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    total = args.train_scenes + args.heldout_scenes
    root = write_dataset(
        args.out / "synth", scenes=total, seed=11, width=args.size[0], height=args.size[1], progress=False
    ).root
    (root / "bench_train.txt").write_text("".join(split_line(i) + "\n" for i in range(args.train_scenes)))
    (root / "bench_heldout.txt").write_text("".join(split_line(i) + "\n" for i in range(args.train_scenes, total)))
    train_set, held_out = SyntheticDataset(root, "bench_train"), SyntheticDataset(root, "bench_heldout")
    score = lambda m: evaluate(m, held_out, device=device, max_disp=args.max_disp).mean  # noqa: E731

    seed_everything(0)
    model = EMCStereo(max_disp=args.max_disp)
    print(f"CPU: {cpu_name()}")
    print(
        f"device {device}, threads {torch.get_num_threads()}, {args.train_scenes} train / {args.heldout_scenes} "
        f"held-out scenes {args.size[0]}×{args.size[1]}, crop {args.crop[0]}×{args.crop[1]}, max_disp {args.max_disp}"
    )
    print(f"{'stage':<28}{'EPE':>8}{'D1':>8}{'Bad-3':>8}{'s/iter':>8}")
    rows: list[dict] = []

    def report(stage: str, metrics: dict, seconds_per_step: float | None) -> None:
        print(row(stage, metrics, seconds_per_step), flush=True)
        rows.append({"stage": stage, **{k: float(v) for k, v in metrics.items()}, "s_per_step": seconds_per_step})

    report("untrained", score(model.to(device)), None)
    started = time.perf_counter()
    trainer = Trainer(
        recipe(root, args.out / "supervised", args, args.steps, args.lr, len(train_set)),
        model,
        train_set,
        None,
        context=DistributedContext(device=device),
        show_progress=False,
    )
    result = trainer.fit()
    per_step = (time.perf_counter() - started) / max(1, result.steps)
    report(f"supervised {result.steps} steps", score(model), per_step)
    if args.selfsup_steps:
        config = recipe(root, args.out / "selfsup", args, args.selfsup_steps, args.lr / 5, len(held_out))
        config = build_config({**config.to_dict(), "data": {**config.to_dict()["data"], "color_jitter": False}})
        started = time.perf_counter()
        ss = SelfSupervisedTrainer(
            config,
            model,
            WithoutGroundTruth(held_out),
            None,
            selfsup=SelfSupConfig(),
            context=DistributedContext(device=device),
            show_progress=False,
        ).fit()
        per_step = (time.perf_counter() - started) / max(1, ss.steps)
        report(f"+ self-supervised {ss.steps} steps", score(model), per_step)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        settings = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
        args.json.write_text(json.dumps({"cpu": cpu_name(), "settings": settings, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
