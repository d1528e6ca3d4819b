"""Evaluating a stereo model on a dataset: the paper's table, per-image averaged.

Each pair is padded at the top and right to the network's sizes (×32, ≥256; edge mode), run in
eval mode at batch 1, and the prediction is un-padded (`[top:, :W−right]`) before any metric.
Metrics come from `stereo.metrics` (per image over valid pixels, then averaged over images).
An image without valid ground truth is *skipped*; an image whose prediction is NaN/Inf at a valid
pixel *failed* (logged, not averaged) and makes the split's `selection_epe` infinite, so a
diverged model is never kept as the best checkpoint. Results go to a JSON file and a text table;
the first N pairs can be drawn as left image / prediction / ground truth, prediction and ground
truth on the same colour scale.
"""

from __future__ import annotations

import json
import logging
import math
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from stereo.datasets.transforms import to_network_input
from stereo.io import colorize_disparity, write_rgb
from stereo.metrics import MetricAverager, valid_mask
from stereo.padding import compute_padding, pad_image, unpad
from stereo.progress import progress_bar

#: The columns of the paper's table, in its order, and how the text report names them.
PAPER_COLUMNS = {
    "epe": "EPE",
    "d1_all": "D1-all",
    "bad_1": "Bad-1",
    "bad_3": "Bad-3",
    "rmse": "RMSE",
    "abs_rel": "AbsRel",
    "delta1": "δ1",
}

log = logging.getLogger(__name__)


@dataclass
class EvaluationResult:
    """Metrics averaged over the scored images, the per-image metrics (with names), and the names of
    images skipped (no valid ground truth) or failed (non-finite prediction at a valid pixel).

    `mean` is empty when no image was scored.
    """

    mean: dict[str, float]
    per_image: list[dict[str, Any]] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)

    @property
    def selection_epe(self) -> float:
        """The EPE that model selection compares: the mean EPE, or +inf when any image failed or none was scored."""
        if self.failed or not self.per_image:
            return math.inf
        return self.mean["epe"]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "images": len(self.per_image),
            "skipped": self.skipped,
            "failed": self.failed,
            "mean": self.mean,
            "per_image": self.per_image,
        }


def autocast_context(device: torch.device, precision: str) -> AbstractContextManager:
    """torch.autocast for "fp16"/"bf16" on `device`, or a no-op for "fp32"."""
    if precision == "fp32":
        return nullcontext()
    dtype = {"fp16": torch.float16, "bf16": torch.bfloat16}[precision]
    return torch.autocast(device_type=device.type, dtype=dtype)


@torch.no_grad()
def predict_disparity(
    model: nn.Module, left: torch.Tensor, right: torch.Tensor, precision: str = "fp32"
) -> torch.Tensor:
    """Disparity `(B,H,W)` px of normalised `(B,3,H,W)` inputs of any size: pad top/right, run, un-pad."""
    padding = compute_padding(left.shape[-2], left.shape[-1])
    was_training = model.training
    model.eval()
    try:
        with autocast_context(left.device, precision):
            out = model(pad_image(left, padding), pad_image(right, padding))
    finally:
        model.train(was_training)
    if isinstance(out, (list, tuple)):
        out = out[-1]
    return unpad(out.float(), padding)


def disparity_panel(left: np.ndarray, prediction: np.ndarray, gt: np.ndarray, max_disp: float) -> np.ndarray:
    """RGB `uint8` `3H×W×3`: the left image over the prediction over the ground truth, one colour scale.

    The scale's top is the largest valid ground truth (or prediction when there is none), capped at `max_disp`.
    """
    valid_gt = gt[np.isfinite(gt) & (gt > 0)]
    top = float(valid_gt.max()) if valid_gt.size else float(np.nanmax(prediction, initial=1.0))
    top = max(1e-3, min(top, max_disp))
    return np.concatenate(
        [left, colorize_disparity(prediction, max_disp=top), colorize_disparity(gt, max_disp=top)], axis=0
    )


def evaluate(
    model: nn.Module,
    dataset: Any,
    *,
    device: torch.device | str = "cpu",
    max_disp: float = 192.0,
    limit: int = 0,
    precision: str = "fp32",
    vis_dir: Path | None = None,
    vis_count: int = 0,
    progress: bool = False,
) -> EvaluationResult:
    """Score `model` on the raw samples of `dataset` (the first `limit` when > 0); draw the first `vis_count`."""
    device = torch.device(device)
    averager = MetricAverager(max_disp=max_disp)
    result = EvaluationResult(mean={})
    count = len(dataset) if limit <= 0 else min(limit, len(dataset))
    for index in progress_bar(iterable=range(count), desc="evaluate", disable=not progress, leave=False):
        raw = dataset[index]
        sample = to_network_input(raw)
        pred = (
            predict_disparity(model, sample["left"][None].to(device), sample["right"][None].to(device), precision)[0]
            .cpu()
            .numpy()
        )
        gt = raw["disparity"]
        name = str(raw["meta"]["name"])
        if not np.isfinite(pred[valid_mask(gt, max_disp)]).all():
            log.warning("%s: the prediction is NaN/Inf at valid ground-truth pixels; image counted as failed", name)
            result.failed.append(name)
        elif (metrics := averager.update(pred, gt)) is None:
            result.skipped.append(name)
        else:
            result.per_image.append({"name": name, **metrics})
        if vis_dir is not None and index < vis_count:
            vis_dir.mkdir(parents=True, exist_ok=True)
            write_rgb(vis_dir / f"{index:04d}.png", disparity_panel(raw["left"], pred, gt, max_disp))
    if averager.count:
        result.mean = averager.mean()
    else:
        log.warning(
            "no image of %d could be scored (%d without valid ground truth, %d failed)",
            count,
            len(result.skipped),
            len(result.failed),
        )
    return result


def format_table(results: dict[str, EvaluationResult]) -> str:
    """A text table of the paper's columns, one row per split name (`images` scored, `failed` non-finite)."""
    header = f"{'split':<12}{'images':>8}{'failed':>8}" + "".join(f"{label:>10}" for label in PAPER_COLUMNS.values())
    lines = [header]
    for split, result in results.items():
        cells = "".join(f"{result.mean.get(key, float('nan')):>10.4f}" for key in PAPER_COLUMNS)
        lines.append(f"{split:<12}{len(result.per_image):>8}{len(result.failed):>8}{cells}")
    return "\n".join(lines) + "\n"


def write_reports(
    results: dict[str, EvaluationResult], out_dir: Path, extra: dict[str, Any] | None = None
) -> tuple[Path, Path]:
    """Write `metrics.json` (per split: mean and per-image metrics) and `metrics.txt` (the table)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path, text_path = out_dir / "metrics.json", out_dir / "metrics.txt"
    payload = {**(extra or {}), "splits": {name: r.to_dict() for name, r in results.items()}}
    json_path.write_text(json.dumps(payload, indent=2), encoding="utf-8")
    text_path.write_text(format_table(results), encoding="utf-8")
    return json_path, text_path


__all__ = [
    "EvaluationResult",
    "autocast_context",
    "disparity_panel",
    "evaluate",
    "format_table",
    "predict_disparity",
    "write_reports",
]
