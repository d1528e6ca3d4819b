"""The training loop of the paper's recipe, resumable at any step and runnable under torchrun.

Per optimiser step: `accumulate` micro-batches, each a forward under autocast (fp16 with a
GradScaler, bf16, or fp32), the deeply supervised loss, backward; then unscale, gradient-norm
clip, AdamW step, per-iteration warm-up + cosine LR, optional weight EMA. A step whose loss or
gradient is non-finite on any process is skipped (weights untouched). After every epoch the main
process validates (EMA weights when EMA is on), keeps `best.pth` by validation EPE, writes
`last.pth` (the full training state), the metrics log and the curve, and stops early after
`patience` epochs without improvement.

Resuming is exact: data order comes from a DistributedSampler seeded by (seed, epoch),
augmentations from (seed, epoch, index), and the checkpoint holds every state plus the position
inside the epoch, so k steps + resume equals the same number of steps in one go.
"""

from __future__ import annotations

import math
import random
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset, DistributedSampler
from tqdm import tqdm

from stereo.checkpoints import CheckpointError, atomic_torch_save
from stereo.datasets.transforms import AsymmetricColorJitter, Augmented, TrainTransform
from stereo.evaluation import autocast_context, evaluate
from stereo.progress import progress_bar
from stereo.training.checkpoint import (
    load_training_checkpoint,
    model_payload,
    restore_training_state,
    save_training_checkpoint,
)
from stereo.training.config import ConfigError, ExperimentConfig
from stereo.training.distributed import DistributedContext
from stereo.training.ema import ModelEMA
from stereo.training.finetune import keep_frozen_in_eval
from stereo.training.loss import LossConfig, disparity_loss
from stereo.training.optim import build_optimizer, build_scheduler
from stereo.training.run_log import RunLog

LAST_CHECKPOINT = "last.pth"
BEST_CHECKPOINT = "best.pth"


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (CPU and CUDA) generators, e.g. before building the model."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    torch.cuda.manual_seed_all(seed)


@dataclass
class TrainResult:
    """How a call to `Trainer.fit` ended."""

    steps: int
    epochs_completed: int
    best_epe: float
    best_epoch: int
    stopped_early: bool
    interrupted: bool
    history: list[dict[str, Any]] = field(default_factory=list)


def _fresh_progress() -> dict[str, Any]:
    """Counters of a run that has not started."""
    return {
        "step": 0,
        "epoch": 0,
        "batch_in_epoch": 0,
        "best_epe": math.inf,
        "best_epoch": -1,
        "bad_epochs": 0,
        "skipped_steps": 0,
        "loss_sum": 0.0,
        "loss_count": 0,
        "history": [],
    }


class Trainer:
    """Trains `model` on raw-sample datasets with the settings of an ExperimentConfig."""

    def __init__(
        self,
        config: ExperimentConfig,
        model: nn.Module,
        train_set: Dataset,
        val_set: Dataset | None,
        *,
        context: DistributedContext = DistributedContext(),
        frozen: tuple[str, ...] = (),
        show_progress: bool = True,
    ) -> None:
        self.config = config
        self.context = context
        self.device = context.device
        self.model = model.to(self.device)
        self.frozen = tuple(frozen)
        self.net = context.wrap(self.model)
        self.val_set = val_set
        self.show_progress = show_progress and context.is_main
        train = config.train
        self.loss_config = LossConfig(
            tuple(train.loss_weights), float(config.model.max_disp), train.clamp_factor, train.loss_cap
        )
        jitter = AsymmetricColorJitter() if config.data.color_jitter else None
        crop_h, crop_w = config.data.crop
        self.train_data = Augmented(
            train_set, TrainTransform(crop_h, crop_w, jitter, float(config.model.max_disp)), seed=train.seed
        )
        self.sampler = DistributedSampler(
            self.train_data,
            num_replicas=context.world_size,
            rank=context.rank,
            shuffle=True,
            seed=train.seed,
            drop_last=context.enabled,
        )
        batches = (
            len(self.sampler) // train.batch_size if train.drop_last else -(-len(self.sampler) // train.batch_size)
        )
        self.steps_per_epoch = batches // train.accumulate
        if self.steps_per_epoch == 0:
            raise ConfigError(
                f"{len(train_set)} training pairs over {context.world_size} process(es) give no full step of "
                f"train.batch_size {train.batch_size} × train.accumulate {train.accumulate}"
            )
        self.micro_batches_per_epoch = self.steps_per_epoch * train.accumulate
        self.total_steps = train.epochs * self.steps_per_epoch
        optim = config.optim
        self.optimizer = build_optimizer(self.model, optim.lr, optim.weight_decay, tuple(optim.betas))
        self.scheduler = build_scheduler(self.optimizer, optim.warmup_steps, self.total_steps)
        self.scaler = torch.amp.GradScaler(self.device.type, enabled=train.precision == "fp16")
        self.ema = ModelEMA(self.model, train.ema_decay) if train.ema_decay > 0 else None
        self.out_dir = Path(train.out_dir)
        self.progress = _fresh_progress()
        self.log = RunLog(self.out_dir, enabled=context.is_main)
        self._bad_accumulation = False

    # ----------------------------------------------------------------- state
    def resume(self, path: Path) -> None:
        """Continue from a training checkpoint written by this trainer (same config)."""
        payload = load_training_checkpoint(Path(path))
        try:
            self.progress = restore_training_state(
                payload,
                model=self.model,
                optimizer=self.optimizer,
                scheduler=self.scheduler,
                scaler=self.scaler,
                ema=self.ema,
            )
        except CheckpointError as exc:
            raise CheckpointError(f"{path}: {exc}") from exc

    def save_last(self) -> None:
        """Write `last.pth` with the full state (main process only)."""
        if self.context.is_main:
            save_training_checkpoint(
                self.out_dir / LAST_CHECKPOINT,
                model=self.model,
                optimizer=self.optimizer,
                scheduler=self.scheduler,
                scaler=self.scaler,
                ema=self.ema,
                progress=self.progress,
            )
        self.context.barrier()

    def evaluated_model(self) -> nn.Module:
        """The weights validation scores: the EMA shadow when EMA is on, else the live model."""
        return self.ema.module if self.ema is not None else self.model

    # ----------------------------------------------------------------- loop
    def fit(self) -> TrainResult:
        """Train until `epochs`, `max_steps` or early stopping; return how it ended."""
        train = self.config.train
        stopped_early = interrupted = False
        try:
            while self.progress["epoch"] < train.epochs:
                epoch_done = self._train_epoch(self.progress["epoch"])
                if not epoch_done:
                    interrupted = True
                    self.save_last()
                    break
                stopped_early = self._end_epoch()
                self.save_last()
                if stopped_early or self._max_steps_reached():
                    interrupted = not stopped_early and self.progress["epoch"] < train.epochs
                    break
        finally:
            self.log.close()
        p = self.progress
        return TrainResult(
            p["step"], p["epoch"], p["best_epe"], p["best_epoch"], stopped_early, interrupted, list(p["history"])
        )

    def _max_steps_reached(self) -> bool:
        limit = self.config.train.max_steps
        return limit > 0 and self.progress["step"] >= limit

    def _epoch_loader(self, epoch: int) -> DataLoader:
        """The epoch's remaining micro-batches, in the seeded order, after those already consumed."""
        self.train_data.set_epoch(epoch)
        self.sampler.set_epoch(epoch)
        batch_size = self.config.train.batch_size
        indices = list(self.sampler)[: self.micro_batches_per_epoch * batch_size]
        start = self.progress["batch_in_epoch"] * batch_size
        return DataLoader(
            self.train_data,
            batch_size=batch_size,
            sampler=indices[start:],
            drop_last=True,
            num_workers=self.config.data.num_workers,
            pin_memory=self.device.type == "cuda",
        )

    def _train_epoch(self, epoch: int) -> bool:
        """Run the rest of `epoch`; False when `max_steps` stopped it before its end."""
        train = self.config.train
        self.net.train()
        keep_frozen_in_eval(self.model, self.frozen)
        bar = progress_bar(
            total=self.micro_batches_per_epoch,
            initial=self.progress["batch_in_epoch"],
            desc=f"epoch {epoch + 1}/{train.epochs}",
            disable=not self.show_progress,
            leave=False,
        )
        started = time.perf_counter()
        try:
            for batch in self._epoch_loader(epoch):
                boundary = (self.progress["batch_in_epoch"] + 1) % train.accumulate == 0
                sync = nullcontext() if boundary or not self.context.enabled else self.net.no_sync()
                with sync:
                    loss = self._backward(batch)
                self.progress["batch_in_epoch"] += 1
                bar.update(1)
                if loss is not None:
                    self.progress["loss_sum"] += loss
                    self.progress["loss_count"] += 1
                if not boundary:
                    continue
                self._optimizer_step()
                self._after_step(bar, loss)
                if self._max_steps_reached() and self.progress["batch_in_epoch"] < self.micro_batches_per_epoch:
                    return False
        finally:
            bar.close()
        self.progress["epoch_seconds"] = self.progress.get("epoch_seconds", 0.0) + time.perf_counter() - started
        return True

    def compute_loss(self, batch: dict[str, Any]) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Forward of one micro-batch (on the device) and its loss: (scalar loss, the predictions)."""
        with autocast_context(self.device, self.config.train.precision):
            predictions = self.net(batch["left"], batch["right"])
        loss, _ = disparity_loss(predictions, batch["disparity"], self.loss_config)
        return loss, predictions

    def _backward(self, batch: dict[str, Any]) -> float | None:
        """Forward, loss and (scaled) backward of one micro-batch; the loss, or None when non-finite."""
        batch = {
            k: v.to(self.device, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()
        }
        loss, predictions = self.compute_loss(batch)
        if not bool(torch.isfinite(loss)):
            # Every process must still run backward (DDP all-reduces inside it); this one adds nothing.
            self._bad_accumulation = True
            loss = 0.0 * sum(p.float().nan_to_num(0.0, 0.0, 0.0).sum() for p in predictions)
            self.scaler.scale(loss).backward()
            return None
        self.scaler.scale(loss / self.config.train.accumulate).backward()
        return float(loss.detach())

    def _optimizer_step(self) -> None:
        """Clip and apply the accumulated gradient, unless any process saw a non-finite loss or gradient."""
        params = [p for p in self.model.parameters() if p.requires_grad]
        skip = self.context.all_reduce_mean(1.0 if self._bad_accumulation else 0.0) > 0
        if not skip:
            self.scaler.unscale_(self.optimizer)
            clip = self.config.train.grad_clip
            norm = torch.nn.utils.clip_grad_norm_(params, clip if clip > 0 else math.inf)
            # With a scaler, overflow is routine: scaler.step skips it and lowers the scale.
            skip = not self.scaler.is_enabled() and not bool(torch.isfinite(norm))
        if skip:
            self.progress["skipped_steps"] += 1
        else:
            self.scaler.step(self.optimizer)
            self.scaler.update()
            if self.ema is not None:
                self.ema.update(self.model)
        self.optimizer.zero_grad(set_to_none=True)
        self.scheduler.step()
        self._bad_accumulation = False
        self.progress["step"] += 1

    def _after_step(self, bar: tqdm, loss: float | None) -> None:
        """Progress bar, step logging and the periodic mid-epoch checkpoint."""
        step = self.progress["step"]
        train = self.config.train
        lr = self.optimizer.param_groups[0]["lr"]
        if loss is not None and train.log_every > 0 and step % train.log_every == 0:
            bar.set_postfix(loss=f"{loss:.4f}", lr=f"{lr:.2e}", refresh=False)  # shown at the next redraw
            self.log.scalar("train/loss", loss, step)
            self.log.scalar("train/lr", lr, step)
        if train.checkpoint_every > 0 and step % train.checkpoint_every == 0:
            self.save_last()

    def _end_epoch(self) -> bool:
        """Validate, record the epoch, keep the best checkpoint; True when early stopping triggers."""
        p, train = self.progress, self.config.train
        mean_loss = p["loss_sum"] / p["loss_count"] if p["loss_count"] else math.nan
        row: dict[str, Any] = {
            "epoch": p["epoch"] + 1,
            "step": p["step"],
            "train_loss": self.context.all_reduce_mean(mean_loss),
            "lr": self.optimizer.param_groups[0]["lr"],
            "skipped_steps": p["skipped_steps"],
            "seconds": round(p.pop("epoch_seconds", 0.0), 3),
        }
        stop = False
        if self.context.is_main and self.val_set is not None:
            result = evaluate(
                self.evaluated_model(),
                self.val_set,
                device=self.device,
                max_disp=self.config.model.max_disp,
                limit=train.val_max_images,
                vis_dir=self.out_dir / "vis" if train.vis_count > 0 else None,
                vis_count=train.vis_count,
            )
            row.update({f"val_{k}": v for k, v in result.mean.items()})
            # A NaN/Inf prediction on any validation image makes the epoch's EPE inf: never the best.
            row.update(val_epe=result.selection_epe, val_failed=len(result.failed))
            if row["val_epe"] < p["best_epe"]:
                p.update(best_epe=row["val_epe"], best_epoch=row["epoch"], bad_epochs=0)
                best = model_payload(self.evaluated_model())
                best.update(epoch=row["epoch"], step=p["step"], val_metrics=result.mean)
                atomic_torch_save(best, self.out_dir / BEST_CHECKPOINT)
            else:
                p["bad_epochs"] += 1
            stop = train.patience > 0 and p["bad_epochs"] >= train.patience
        p["history"].append(row)
        self.log.write_epochs(p["history"])
        p.update(epoch=p["epoch"] + 1, batch_in_epoch=0, loss_sum=0.0, loss_count=0)
        return self.context.broadcast_flag(stop)
