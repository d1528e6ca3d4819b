"""Putting a run together from a config: model (fresh or warm-started), frozen modules, data, trainer.

Shared by `emcstereo train` and `emcstereo finetune`, and usable from Python.
"""

from __future__ import annotations

from pathlib import Path

from torch.utils.data import Dataset

from stereo.model import MIN_SIZE, EMCStereo
from stereo.training.config import ConfigError, ExperimentConfig
from stereo.training.data import train_val_datasets
from stereo.training.distributed import DistributedContext
from stereo.training.finetune import freeze, warm_start
from stereo.training.selfsup import SelfSupConfig, SelfSupervisedTrainer
from stereo.training.trainer import LAST_CHECKPOINT, Trainer, TrainResult, seed_everything


def build_model(config: ExperimentConfig) -> EMCStereo:
    """A fresh EMCStereo of the configured variant, or the warm start of `finetune.weights`."""
    if min(config.data.crop) < MIN_SIZE:
        raise ConfigError(f"data.crop {list(config.data.crop)}: EMCStereo needs both sides ≥ {MIN_SIZE}")
    if config.finetune.weights:
        return warm_start(config.finetune.weights, config.model)
    return EMCStereo.from_config(config.model)


def resolve_resume(config: ExperimentConfig, resume: str | None) -> Path | None:
    """The checkpoint to resume from: a path, "auto" (the run's `last.pth` when present), or None."""
    if not resume:
        return None
    if resume == "auto":
        last = Path(config.train.out_dir) / LAST_CHECKPOINT
        return last if last.is_file() else None
    path = Path(resume)
    if not path.is_file():
        raise ConfigError(f"--resume {resume}: no such checkpoint")
    return path


def run_training(
    config: ExperimentConfig,
    *,
    context: DistributedContext = DistributedContext(),
    resume: str | None = None,
    show_progress: bool = True,
    selfsup: SelfSupConfig | None = None,
    train_set: Dataset | None = None,
) -> TrainResult:
    """Seed, build, (resume,) train. `train_set` replaces the config's training data (e.g. unlabelled pairs)."""
    seed_everything(config.train.seed)
    model = build_model(config)
    frozen = tuple(config.finetune.freeze)
    freeze(model, frozen)
    if train_set is None:
        train_set, val_set = train_val_datasets(config.data)
    else:
        val_set = train_val_datasets(config.data)[1] if config.data.root else None
    kwargs = dict(context=context, frozen=frozen, show_progress=show_progress)
    trainer = (
        SelfSupervisedTrainer(config, model, train_set, val_set, selfsup=selfsup, **kwargs)
        if selfsup is not None
        else Trainer(config, model, train_set, val_set, **kwargs)
    )
    checkpoint = resolve_resume(config, resume)
    if checkpoint is not None:
        trainer.resume(checkpoint)
    return trainer.fit()
