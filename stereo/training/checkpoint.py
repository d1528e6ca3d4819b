"""Training checkpoints: everything needed to continue a run exactly where it stopped.

A training checkpoint is our model-checkpoint layout (`format`, `config`, `model`, readable by
`stereo.load_model`) plus `optimizer`, `scheduler`, `scaler`, `ema`, `rng` (Python, NumPy, torch
CPU and CUDA generators), and the progress counters (`step`, `epoch`, `batch_in_epoch`, best
validation EPE, epochs without improvement, metric history). Files are written to a temporary
name and renamed (`atomic_torch_save`), so a kill at any moment leaves the previous checkpoint whole.
"""
from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from stereo.checkpoints import FORMAT, CheckpointError, atomic_torch_save
from stereo.training.ema import ModelEMA, unwrap


def capture_rng_state() -> dict[str, Any]:
    """The state of every random generator a training step may draw from, weights-only loadable."""
    np_state = np.random.get_state(legacy=True)
    state: dict[str, Any] = {
        "python": random.getstate(),
        "numpy": {
            "key": torch.from_numpy(np_state[1].astype(np.int64)),
            "pos": int(np_state[2]),
            "has_gauss": int(np_state[3]),
            "cached_gaussian": float(np_state[4]),
        },
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: dict[str, Any]) -> None:
    """Put every generator back into the state `capture_rng_state` recorded."""
    random.setstate(state["python"])
    numpy = state["numpy"]
    np.random.set_state(
        ("MT19937", numpy["key"].numpy().astype(np.uint32), numpy["pos"], numpy["has_gauss"], numpy["cached_gaussian"])
    )
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def model_payload(model: nn.Module) -> dict[str, Any]:
    """Model weights in our checkpoint layout (with the variant config when the model has one)."""
    net = unwrap(model)
    payload: dict[str, Any] = {"model": {k: v.detach().cpu() for k, v in net.state_dict().items()}}
    config = getattr(net, "config", None)
    if hasattr(config, "to_dict"):
        payload.update(format=FORMAT, config=config.to_dict())
    return payload


def save_training_checkpoint(
    path: Path,
    *,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.LRScheduler,
    scaler: torch.amp.GradScaler,
    ema: ModelEMA | None,
    progress: dict[str, Any],
) -> Path:
    """Atomically write the full training state; `progress` holds the counters and history."""
    payload = model_payload(model)
    payload.update(
        optimizer=optimizer.state_dict(),
        scheduler=scheduler.state_dict(),
        scaler=scaler.state_dict(),
        ema=None if ema is None else ema.state_dict(),
        rng=capture_rng_state(),
        progress=dict(progress),
    )
    return atomic_torch_save(payload, Path(path))


def load_training_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint written by `save_training_checkpoint` (weights-only unpickling)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such training checkpoint")
    payload = torch.load(path, map_location="cpu", weights_only=True)
    missing = [k for k in ("model", "optimizer", "scheduler", "scaler", "rng", "progress") if k not in payload]
    if missing:
        raise CheckpointError(
            f"{path}: not a training checkpoint (missing {', '.join(missing)}); to start from weights only, "
            "use `emcstereo finetune --weights`"
        )
    return payload


def restore_training_state(
    payload: dict[str, Any],
    *,
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.LRScheduler,
    scaler: torch.amp.GradScaler,
    ema: ModelEMA | None,
) -> dict[str, Any]:
    """Load a training checkpoint into the live objects and return its `progress` counters."""
    unwrap(model).load_state_dict(payload["model"], strict=True)
    optimizer.load_state_dict(payload["optimizer"])
    scheduler.load_state_dict(payload["scheduler"])
    scaler.load_state_dict(payload["scaler"])
    if ema is not None:
        if payload.get("ema") is None:
            raise CheckpointError("the checkpoint was written without EMA weights but this run has EMA on")
        ema.load_state_dict(payload["ema"])
    restore_rng_state(payload["rng"])
    return dict(payload["progress"])
