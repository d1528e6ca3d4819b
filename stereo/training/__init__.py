"""Training EMCStereo: config, loss, optimiser and schedule, EMA, checkpoints, the trainer, DDP,
warm starts and self-supervised fine-tuning. Entry points: `emcstereo train` / `emcstereo finetune`
or `stereo.training.run.run_training(load_config(path))`."""

from stereo.training.config import ConfigError, ExperimentConfig, build_config, load_config
from stereo.training.run import run_training
from stereo.training.trainer import Trainer, TrainResult

__all__ = ["ConfigError", "ExperimentConfig", "TrainResult", "Trainer", "build_config", "load_config", "run_training"]
