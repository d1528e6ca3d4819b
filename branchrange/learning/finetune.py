"""Fine-tuning `BranchNet` on a user's labelled frames, and writing the model bundle it is deployed as.

`finetune_branchnet(config, frames, start, out_dir, data_dir)`:
1. starts from the weights of the ONNX model `start` (the shipped one, or a bundle's:
   `branchnet_from_onnx`), its batch norms held in eval mode;
   keeping its training's class weights and crop draws (`KEPT_TRAINING_SETTINGS`);
2. splits the frames by image, seeded: `holdout_share` of them are never trained on;
3. trains `steps` steps of `batch` crops (the shipped training's crops and augmentation,
   `branchrange.learning.training.training_crop`), a `synthetic_share` of each batch from the synthetic training
   scenes so that what the shipped model learnt is not forgotten, the rest from the user's frames;
4. measures the starting model and the fine-tuned one on the held-out frames (`branchrange.learning.heldout`: pixel
   IoU, cut points judged against the labels) and on the synthetic validation scenes (pixel IoU), and
   calibrates the fine-tuned model's confidence: "on a branch" on the held-out frames, times "within 5 cm
   given on a branch" on synthetic calibration scenes (`branchrange.learning.depth_factor`);
5. writes the bundle (`bundle`): ONNX, torch weights, metadata JSON with the calibration, metrics,
   training curve, manifest — with `int8`, also the model's int8 copy, calibrated on its own.

Why hold the batch norms: their statistics are folded into the shipped convolutions, and batches of 8
crops of a few dozen frames would measure them again badly; the fine-tune moves the weights only.
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from branchrange.core.segmentation.bundle import MODEL_NAME
from branchrange.core.segmentation.learned import verified_metadata
from branchrange.core.segmentation.ood import MIN_REFERENCE_FRAMES, OOD_KEY
from branchrange.learning.branchnet import BranchNet
from branchrange.learning.bundle_writer import write_manifest
from branchrange.learning.coco_labels import LabelledSample, split_by_image
from branchrange.learning.depth_factor import DEPTH_FACTOR_SCENES, depth_factor
from branchrange.learning.from_onnx import branchnet_from_onnx
from branchrange.learning.heldout import (
    HELDOUT_TRUNK_BANDS,
    MIN_CALIBRATION_CUT_POINTS,
    calibration_table,
    frame_width,
    heldout_outcomes,
    scores,
)
from branchrange.learning.ood_reference import model_reference
from branchrange.learning.samples import cached_sample, render_samples
from branchrange.learning.training import (
    BranchNetTrainConfig,
    class_iou,
    export_onnx,
    optimiser_step,
    training_crop,
    weighted_cross_entropy,
)
from stereo.weights import sha256_of

#: at most this many of the frames trained on set an int8 copy's activation ranges
INT8_RANGE_FRAMES = 40
#: the first of the shipped training's validation scenes (2801–2830): what "nothing learnt is forgotten" is measured on
SYNTHETIC_VALIDATION_FIRST = 2801


@dataclass(frozen=True)
class FineTuneConfig:
    """How a fine-tune runs.

    - `steps`, `batch`, `crop`: optimiser steps, crops per step, crop side px (as the shipped training).
    - `lr`, `weight_decay`: AdamW, one cycle (5 % warm-up, then cosine down to 2 % of `lr`); a tenth of
      the shipped training's last stage: the weights are to move, not to start again.
    - `synthetic_share`: share of each batch's crops drawn from synthetic scenes (0..1; a fractional count
      is rounded at random per step), from the first `synthetic_scenes` training seeds (rendered into the
      cache once). Measured: see the manual (segmenter adaptation) for 0 / 25 / 50 %.
    - `validation_scenes`: the shipped training's validation scenes (from `SYNTHETIC_VALIDATION_FIRST`) the
      synthetic IoU is measured on, before, during and after (1..30).
    - `holdout_share`: share of the labelled frames held out (by image, seeded by `seed`).
    - `depth_scenes`: synthetic calibration scenes the depth factor of the confidence is measured on
      (`branchrange.learning.depth_factor`; ~0.7 s each, rendered once into the data folder).
    - `seed`: split, crops, augmentation; `threads`: torch CPU threads; `val_every`: steps between validations.
    """

    steps: int = 1500
    batch: int = 8
    crop: int = 192
    lr: float = 3e-4
    weight_decay: float = 1e-4
    synthetic_share: float = 0.5
    synthetic_scenes: int = 200
    validation_scenes: int = 30
    holdout_share: float = 0.2
    depth_scenes: int = DEPTH_FACTOR_SCENES
    seed: int = 0
    threads: int = 2
    val_every: int = 100

    def __post_init__(self) -> None:
        if self.steps < 1 or self.batch < 1 or self.crop % 16 or self.crop < 64:
            raise ValueError("--steps and batch must be ≥ 1, crop a multiple of 16 and ≥ 64")
        if not 0 <= self.synthetic_share <= 1:
            raise ValueError(f"--synthetic-share {self.synthetic_share}: a share in [0, 1]")
        if not 0 <= self.holdout_share < 1:
            raise ValueError(f"--holdout-share {self.holdout_share}: a share in [0, 1)")
        if not 1 <= self.synthetic_scenes <= 1200:
            raise ValueError(f"synthetic_scenes {self.synthetic_scenes}: 1..1200 (the shipped training's scenes)")
        if not 1 <= self.validation_scenes <= 30:
            raise ValueError(f"validation_scenes {self.validation_scenes}: 1..30 (the shipped training's)")
        if self.val_every < 1 or self.threads < 1:
            raise ValueError("val_every and threads must be ≥ 1")
        if not 1 <= self.depth_scenes <= 240:
            raise ValueError(f"depth_scenes {self.depth_scenes}: 1..240 (the calibration scenes)")


#: the starting model's training settings a fine-tune keeps: the loss's class weights and how crops are drawn
KEPT_TRAINING_SETTINGS = ("class_weights", "branch_crop_share", "instance_balance")


def kept_training_settings(start_meta: dict[str, Any]) -> dict[str, Any]:
    """`KEPT_TRAINING_SETTINGS` of the starting model's JSON: a bundle's "training_settings", else the shipped
    training's "config"; `BranchNetTrainConfig`'s defaults for what neither holds."""
    recorded = start_meta.get("training_settings") or start_meta.get("config") or {}
    defaults = asdict(BranchNetTrainConfig())
    return {
        k: tuple(v) if isinstance(v, list) else v
        for k, v in ((k, recorded.get(k, defaults[k])) for k in KEPT_TRAINING_SETTINGS)
    }


def _iou(model: BranchNet, samples: list[dict[str, np.ndarray]]) -> dict[str, float]:
    """`class_iou`, the model left in eval mode (its batch norms hold their folded statistics)."""
    iou = class_iou(model, samples) if samples else {}
    model.eval()
    return iou


def synthetic_count(share: float, batch: int, rng: np.random.Generator) -> int:
    """How many of a batch's crops are synthetic: share × batch, its fraction rounded up at random."""
    whole = int(share * batch)
    return whole + int(rng.random() < share * batch - whole)


def _train(
    model: BranchNet,
    config: FineTuneConfig,
    kept: dict[str, Any],
    train: Sequence[LabelledSample],
    evaluate: Callable[[BranchNet], dict[str, float]],
    data_dir: Path,
    log: Callable[[str], object],
) -> list[dict[str, Any]]:
    """The training loop of step 3 (module docstring); the curve's rows, one per validation."""
    rng = np.random.default_rng(config.seed)
    crop_config = BranchNetTrainConfig(crop=config.crop, **kept)
    optimiser = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    schedule = torch.optim.lr_scheduler.OneCycleLR(
        optimiser, max_lr=config.lr, total_steps=config.steps, pct_start=0.05, final_div_factor=50
    )
    weights = torch.tensor(crop_config.class_weights, dtype=torch.float32)
    history: list[dict[str, Any]] = []
    running: list[float] = []
    spent, start = 0.0, time.perf_counter()  # training time, validations left out
    for step in range(1, config.steps + 1):
        synthetic = synthetic_count(config.synthetic_share, config.batch, rng)
        samples = [cached_sample(data_dir, 1 + int(rng.integers(config.synthetic_scenes))) for _ in range(synthetic)]
        samples += [train[int(rng.integers(len(train)))].sample for _ in range(config.batch - synthetic)]
        crops = [training_crop(sample, crop_config, rng) for sample in samples]
        inputs = torch.from_numpy(np.stack([c[0] for c in crops])).contiguous(memory_format=torch.channels_last)
        loss = weighted_cross_entropy(
            model(inputs), torch.from_numpy(np.stack([c[1] for c in crops])), weights,
            torch.from_numpy(np.stack([c[2] for c in crops])),
        )  # fmt: skip
        running.append(optimiser_step(loss, optimiser, schedule))
        if step % config.val_every == 0 or step == config.steps:
            spent += time.perf_counter() - start
            row = {"step": step, "train_loss": float(np.mean(running)), **evaluate(model), "seconds": round(spent, 1)}
            start = time.perf_counter()
            history.append(row)
            running = []
            log(" ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
    return history


def _write_curve(out_dir: Path, history: list[dict[str, Any]]) -> None:
    """metrics.csv and training_curve.png of the rows `history` (a value None: not measured, left out)."""
    from stereo.io import write_rgb
    from stereo.training.curves import plot_panel

    with (out_dir / "metrics.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(history[0]))
        writer.writeheader()
        writer.writerows(history)
    steps = [row["step"] for row in history]
    panels = [
        ("train loss", "train_loss", (31, 119, 180)),
        ("held-out IoU branch", "heldout_iou_branch", (214, 39, 40)),
        ("synthetic val IoU branch", "synthetic_iou_branch", (148, 103, 189)),
    ]
    write_rgb(
        out_dir / "training_curve.png",
        np.concatenate([plot_panel(title, steps, [r.get(k) for r in history], c, "step") for title, k, c in panels], 1),
    )


def _heldout(model: Path, frames: Sequence[LabelledSample], iou: dict[str, float]) -> tuple[dict, dict]:
    """Per trunk band of `HELDOUT_TRUNK_BANDS`: the `scores` of the ONNX `model` on held-out `frames`, and the
    (raw confidence, right) outcomes the calibration is fitted on."""
    figures, outcomes = {}, {}
    for band in HELDOUT_TRUNK_BANDS:
        outcomes[band], counts = heldout_outcomes(model, frames, band)
        figures[f"trunk_band_{band}"] = scores(counts, iou)
    return figures, outcomes


def _ood_reference(
    model: Path, frames: Sequence[LabelledSample], log: Callable[[str], object]
) -> dict[str, Any] | None:
    """The fine-tuned `model`'s out-of-distribution reference (`branchrange.learning.ood_reference`, as its JSON
    stores it under `ood.OOD_KEY`), measured on the user's labelled frames — the domain it was adapted to, with
    the stereo it was recorded with — so that at run time the signal says when a frame does not look like them. Too few
    frames: None (the bundle then gives no signal) and the log says so."""
    if len(frames) < MIN_REFERENCE_FRAMES:
        log(
            f"{len(frames)} labelled frames: an out-of-distribution reference needs {MIN_REFERENCE_FRAMES}; "
            "this bundle gives no out-of-distribution signal"
        )
        return None
    domain = f"{len(frames)} labelled frames of the fine-tune ({frames[0].name} …)"
    reference = model_reference(model, ((f.sample["left"], f.sample["disparity"]) for f in frames), domain)
    log(f"out-of-distribution reference from {reference.frames} frames, flagged beyond {reference.threshold:.2f}")
    return reference.to_json_dict()


def _calibrated(
    model: Path,
    meta: dict[str, Any],
    held: Sequence[LabelledSample],
    frames: Sequence[LabelledSample],
    iou: dict[str, float],
    config: FineTuneConfig,
    data_dir: Path,
    log: Callable[[str], object],
) -> dict[str, Any]:
    """Calibrate the ONNX `model` (its JSON `meta` already beside it): per trunk band, its cut points on the
    `held` frames ("on a labelled branch") times its depth factor on synthetic scenes
    (`branchrange.learning.depth_factor`), and its out-of-distribution reference on all labelled `frames`; `meta`
    with them is written again. Returns its held-out figures per band (with the pixel `iou` given, measured in
    torch)."""
    figures, outcomes = _heldout(model, held, iou)
    meta["confidence_calibrations"] = []
    for band in HELDOUT_TRUNK_BANDS:
        if len(outcomes.get(band, [])) < MIN_CALIBRATION_CUT_POINTS:
            log(
                f"{model.name}, trunk band {band} px: {len(outcomes.get(band, []))} held-out cut points, too few to "
                "calibrate their confidence (label more frames, or hold out a larger share): its cut points are "
                "never targets"
            )
            continue
        depth = depth_factor(model, config.depth_scenes, band, data_dir, log)
        table = calibration_table(outcomes[band], frame_width(held), band, depth)
        if table is None:
            log(
                f"{model.name}, trunk band {band} px: no depth factor, so no calibration: its cut points are never "
                "targets"
            )
        else:
            meta["confidence_calibrations"].append(table)
    reference = _ood_reference(model, frames, log)
    if reference is not None:
        meta[OOD_KEY] = reference
    model.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    return figures


def finetune_branchnet(
    config: FineTuneConfig,
    frames: Sequence[LabelledSample],
    start: Path,
    out_dir: Path,
    data_dir: Path,
    log: Callable[[str], object] = print,
    workers: int = 1,
    version: str = "",
    int8: bool = False,
) -> dict[str, Any]:
    """Fine-tune and write the bundle (module docstring) to `out_dir`; returns its metrics.json. Synthetic
    scenes not yet in `data_dir` are rendered first in `workers` processes. With `int8`, also its statically
    quantized copy (`branchrange.learning.quantize`, activation ranges from the frames trained on), calibrated on its
    own. ValueError for too few frames."""
    if len(frames) < 2 and config.holdout_share > 0:
        raise ValueError(f"{len(frames)} labelled frame: at least 2 (one to train on, one held out)")
    start_meta = verified_metadata(start)
    width, fine_width = int(start_meta.get("width", 12)), int(start_meta.get("fine_width", 0))
    deep_blocks = int(start_meta.get("deep_blocks", 0))
    torch.manual_seed(config.seed)
    torch.set_num_threads(config.threads)
    model = branchnet_from_onnx(start, width, fine_width, deep_blocks)
    train_at, held_at = split_by_image(len(frames), config.holdout_share, config.seed)
    train, held = [frames[i] for i in train_at], [frames[i] for i in held_at]
    log(f"{len(train)} frames to train on, {len(held)} held out: {', '.join(f.name for f in held) or 'none'}")
    seeds = [(s, False) for s in range(1, 1 + config.synthetic_scenes if config.synthetic_share else 1)]
    validation_seeds = range(SYNTHETIC_VALIDATION_FIRST, SYNTHETIC_VALIDATION_FIRST + config.validation_scenes)
    rendered = render_samples(data_dir, [*seeds, *((s, False) for s in validation_seeds)], workers)
    if rendered:
        log(f"rendered {rendered} synthetic scenes into {data_dir}")
    validation = [cached_sample(data_dir, s) for s in validation_seeds]
    held_samples = [f.sample for f in held]

    def evaluate(network: BranchNet) -> dict[str, float]:
        found = {f"heldout_iou_{k}": v for k, v in _iou(network, held_samples).items() if k != "background"}
        return found | {f"synthetic_iou_{k}": v for k, v in _iou(network, validation).items() if k != "background"}

    before = evaluate(model)
    out_dir.mkdir(parents=True, exist_ok=True)
    model = model.to(memory_format=torch.channels_last)
    kept = kept_training_settings(start_meta)
    history = _train(model, config, kept, train, evaluate, data_dir, log)
    seconds = float(history[-1]["seconds"])
    _write_curve(out_dir, [{"step": 0, "train_loss": None, **before, "seconds": 0.0}, *history])  # from the start
    torch.save(model.state_dict(), out_dir / "branchnet.pt")
    onnx_sha256 = export_onnx(model, out_dir / MODEL_NAME)
    after = history[-1]
    heldout_before, _ = _heldout(
        start, held, {k[len("heldout_iou_") :]: v for k, v in before.items() if "heldout" in k}
    )
    meta: dict[str, Any] = {
        "model": "BranchNet",
        "width": width,
        "fine_width": fine_width,
        "deep_blocks": deep_blocks,
        "classes": start_meta.get("classes"),
        "onnx_sha256": onnx_sha256,
        "config": asdict(config),
        "training_settings": kept,
        "init_sha256": sha256_of(start),
        "final": after,
        "torch": torch.__version__,
        "finetune": {"train_frames": [f.name for f in train], "heldout_frames": [f.name for f in held]},
        "confidence_calibrations": [],
    }
    (out_dir / "branchnet.json").write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    heldout_iou = {k[len("heldout_iou_") :]: v for k, v in after.items() if "heldout" in k}
    heldout_after = _calibrated(out_dir / MODEL_NAME, meta, held, frames, heldout_iou, config, data_dir, log)
    heldout_int8 = None
    if int8:
        from branchrange.learning.quantize import int8_path, quantize_branchnet

        samples = [f.sample for f in train][:INT8_RANGE_FRAMES]
        int8_meta = quantize_branchnet(
            out_dir / MODEL_NAME, data_dir, samples=samples, samples_from=f"{len(samples)} labelled frames (trained on)"
        )
        log(f"wrote {int8_path(out_dir / MODEL_NAME).name}; calibrating it on its own")
        heldout_int8 = _calibrated(int8_path(out_dir / MODEL_NAME), int8_meta, held, frames, {}, config, data_dir, log)
    metrics = {
        "heldout": {
            "frames": len(held),
            "before": heldout_before,
            "after": heldout_after,
            **({"after_int8": heldout_int8} if heldout_int8 is not None else {}),
        },
        "synthetic_validation": {
            "seeds": [validation_seeds.start, validation_seeds.stop],
            "before": {k: round(v, 4) for k, v in before.items() if k.startswith("synthetic")},
            "after": {k: round(v, 4) for k, v in after.items() if k.startswith("synthetic")},
        },
        "training": {
            "frames": len(train),
            "steps": config.steps,
            "seconds": round(seconds, 1),
            "seconds_per_step": round(seconds / config.steps, 3),
            "threads": config.threads,
            "started_from": {"file": str(start), "onnx_sha256": sha256_of(start)},
        },
    }
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n", encoding="utf-8")
    write_manifest(out_dir, sorted({(f.sample["left"].shape[1], f.sample["left"].shape[0]) for f in frames}), version)
    return metrics
