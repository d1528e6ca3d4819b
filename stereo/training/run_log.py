"""Per-epoch records of a training run: CSV, JSON, the training-curve PNG and, if installed, TensorBoard.

Only the main process writes. The history lives in the training checkpoint too, so a resumed run
rewrites complete files.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from stereo.training.curves import write_training_curve


def open_tensorboard(log_dir: Path) -> Any | None:
    """A TensorBoard SummaryWriter when the `tensorboard` package is installed, else None."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(log_dir=str(log_dir))


def _json_safe(history: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The history with NaN/Inf floats (e.g. the EPE of a failed validation) as null, which strict JSON allows."""
    return [
        {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in row.items()} for row in history
    ]


class RunLog:
    """Writes `metrics.csv`, `metrics.json` and `training_curve.png` under `out_dir` after every epoch."""

    def __init__(self, out_dir: Path, enabled: bool = True) -> None:
        self.out_dir = Path(out_dir)
        self.enabled = enabled
        self.tensorboard = open_tensorboard(self.out_dir / "tensorboard") if enabled else None

    def scalar(self, name: str, value: float, step: int) -> None:
        """Send one step-level value to TensorBoard (when available)."""
        if self.tensorboard is not None:
            self.tensorboard.add_scalar(name, value, step)

    def write_epochs(self, history: Sequence[dict[str, Any]]) -> None:
        """Rewrite the CSV, JSON and PNG from the full per-epoch history."""
        if not self.enabled or not history:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        columns: list[str] = []
        for row in history:
            columns.extend(k for k in row if k not in columns)
        with open(self.out_dir / "metrics.csv", "w", newline="", encoding="utf-8") as handle:
            writer = csv.DictWriter(handle, fieldnames=columns)
            writer.writeheader()
            writer.writerows(history)
        (self.out_dir / "metrics.json").write_text(json.dumps(_json_safe(history), indent=2), encoding="utf-8")
        write_training_curve(history, self.out_dir / "training_curve.png")
        if self.tensorboard is not None:
            last = history[-1]
            for key, value in last.items():
                if key != "epoch" and isinstance(value, (int, float)):
                    self.tensorboard.add_scalar(f"epoch/{key}", value, last["epoch"])
            self.tensorboard.flush()

    def close(self) -> None:
        """Flush and close TensorBoard."""
        if self.tensorboard is not None:
            self.tensorboard.close()
