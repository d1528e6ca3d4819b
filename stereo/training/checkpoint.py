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

from stereo.checkpoints import FORMAT, CheckpointError, atomic_torch_save, torch_load_checked
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
    payload = torch_load_checked(path)
    if not isinstance(payload, dict):
        raise CheckpointError(f"{path}: not a training checkpoint (a {type(payload).__name__}, not a dict)")
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
    """Load a training checkpoint into the live objects and return its `progress` counters.

    A payload that does not fit this run (other variant, other optimiser groups, damaged entries)
    raises `CheckpointError` saying which part failed, never a bare traceback.
    """
    if ema is not None and payload.get("ema") is None:
        raise CheckpointError("the checkpoint was written without EMA weights but this run has EMA on")
    steps = [
        ("model", lambda: unwrap(model).load_state_dict(payload["model"], strict=True)),
        ("optimizer", lambda: optimizer.load_state_dict(payload["optimizer"])),
        ("scheduler", lambda: scheduler.load_state_dict(payload["scheduler"])),
        ("scaler", lambda: scaler.load_state_dict(payload["scaler"])),
        ("ema", lambda: ema is None or ema.load_state_dict(payload["ema"])),
        ("rng", lambda: restore_rng_state(payload["rng"])),
    ]
    for part, load in steps:
        try:
            load()
        except (RuntimeError, ValueError, KeyError, TypeError, IndexError, AttributeError) as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise CheckpointError(f"the checkpoint's `{part}` does not fit this run: {first}") from exc
    return dict(payload["progress"])
