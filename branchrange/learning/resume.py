"""Exact resume of a `train_branchnet` run: its state at a validation, saved and put back.

Why: a run on the randomized domain goes unattended for hours; killed (a reboot, a lost session), it must
continue where it stopped and end with the weights an uninterrupted run would have had, or the recipe's
"same config → same weights" no longer holds. The state is everything a step reads: the model, the
optimiser's moments, the learning-rate schedule, the crop generator (a NumPy `Generator`), torch's own
generators and the step; plus the metrics rows so far. `branchrange.learning.training` writes it to
`CHECKPOINT_NAME` in the run's folder at every validation (`val_every` steps), under a temporary name renamed
in place (`stereo.checkpoints.atomic_torch_save`): a kill at any moment leaves the previous one whole.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from stereo.checkpoints import atomic_torch_save
from stereo.training.checkpoint import capture_rng_state, restore_rng_state

CHECKPOINT_NAME = "checkpoint.pt"


def save_training_state(
    path: Path,
    settings: dict[str, Any],
    step: int,
    model: torch.nn.Module,
    optimiser: torch.optim.Optimizer,
    schedule: Any,
    rng: np.random.Generator,
    history: list[dict[str, Any]],
) -> None:
    """Write the state of the run of `settings` (its `BranchNetTrainConfig` as a dict) after `step` optimiser
    steps to `path` (weights-only loadable: the settings, the generator's state and the metrics rows travel as
    JSON text)."""
    state = {
        "config": json.dumps(settings, sort_keys=True),
        "step": step,
        "model": model.state_dict(),
        "optimiser": optimiser.state_dict(),
        "schedule": schedule.state_dict(),
        "crop_rng": json.dumps(rng.bit_generator.state),
        "torch_rng": capture_rng_state(),
        "history": json.dumps(history),
    }
    atomic_torch_save(state, path)


def restore_training_state(
    path: Path,
    settings: dict[str, Any],
    model: torch.nn.Module,
    optimiser: torch.optim.Optimizer,
    schedule: Any,
    rng: np.random.Generator,
) -> tuple[int, list[dict[str, Any]]]:
    """Put the state saved at `path` back into `model`, `optimiser`, `schedule`, `rng` and torch's generators;
    (steps done, metrics rows so far). ValueError for a missing or unreadable file, or one saved by a run of
    other `settings` (resuming it would mix two runs)."""
    if not path.is_file():
        raise ValueError(f"resume: no checkpoint {path} (a run writes one at its first validation)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        saved = json.loads(state["config"])
    except (OSError, RuntimeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"resume: {path} is not a train-segmenter checkpoint ({exc})") from None
    changed = sorted(key for key, value in json.loads(json.dumps(settings)).items() if saved.get(key) != value)
    if changed:
        raise ValueError(f"resume: {path} was saved by a run with other settings ({', '.join(changed)})")
    model.load_state_dict(state["model"])
    optimiser.load_state_dict(state["optimiser"])
    schedule.load_state_dict(state["schedule"])
    rng.bit_generator.state = json.loads(state["crop_rng"])
    restore_rng_state(state["torch_rng"])
    return int(state["step"]), json.loads(state["history"])
