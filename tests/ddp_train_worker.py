"""One process of the DDP test, started twice by torchrun.

Usage: ddp_train_worker.py CONFIG.toml OUT_DIR [EMCSTEREO ARGS...]

First it trains TinyStereoNet with the real Trainer and writes this rank's trainable parameters
(before and after) and the sample indices its sampler drew in epoch 0 to OUT_DIR/rank{R}.pt;
checkpoints and logs go to OUT_DIR/run_rank{R}, so the test can see which ranks wrote them. Then,
when EMCSTEREO ARGS are given, it runs the `emcstereo` console entry point (`stereo.cli.main`) with
them in the same process group — the real command under torchrun — and exits with its status.
Sharing one launch keeps the test to a single torchrun start-up.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stereo_training_fixtures import TinyStereoNet  # noqa: E402

from stereo.cli import main as emcstereo  # noqa: E402
from stereo.training.config import load_config  # noqa: E402
from stereo.training.data import train_val_datasets  # noqa: E402
from stereo.training.distributed import context_from_env, shutdown  # noqa: E402
from stereo.training.trainer import Trainer, seed_everything  # noqa: E402


def main(config_path: str, out_dir: str, emcstereo_args: list[str]) -> int:
    torch.set_num_threads(1)
    context = context_from_env(os.environ, device="cpu", backend="gloo")
    out = Path(out_dir)
    config = load_config(config_path, [f'train.out_dir="{out / f"run_rank{context.rank}"}"'])
    seed_everything(config.train.seed)
    model = TinyStereoNet(max_disp=config.model.max_disp)
    initial = {n: p.detach().clone() for n, p in model.named_parameters()}
    train_set, val_set = train_val_datasets(config.data)
    trainer = Trainer(config, model, train_set, val_set, context=context, show_progress=False)
    trainer.sampler.set_epoch(0)
    seen = list(trainer.sampler)
    result = trainer.fit()
    torch.save(
        {
            "params": {n: p.detach().clone() for n, p in model.named_parameters()},
            "initial": initial,
            "seen": seen,
            "steps": result.steps,
            "world_size": context.world_size,
        },
        out / f"rank{context.rank}.pt",
    )
    if not emcstereo_args:
        shutdown(context)
        return 0
    return emcstereo(emcstereo_args)  # joins the initialised group, leaves it at the end


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2], sys.argv[3:]))
