"""Training `BranchNet` on CPU from synthetic scenes, and exporting it to the ONNX file the segmenter ships.

`train_branchnet(config, out_dir, data_dir)`: renders (or reads cached, in `data_dir`) training scenes,
trains with random crops and strong photometric randomisation, validates on scenes kept apart from
training, writes `metrics.csv`, `training_curve.png`, `branchnet.pt` (torch weights), `branchnet.onnx`
and `branchnet.json` (config, seed, per-class IoU, the ONNX file's SHA-256); the confidence
calibration is a separate step (`branchrange.learning.calibration`), run by `branchrange train-segmenter`. Same
config + same cached scenes → the same weights (torch's CPU kernels are deterministic at a fixed thread
count; a test trains twice and compares).

Why these augmentations: the real trees are not the synthetic ones. Scale (0.5–1.6×) covers other
focal lengths and branch widths; gain, contrast, gamma, per-channel colour, greyscale (some stereo
cameras are monochrome), blur and noise cover exposure, white balance, focus and sensor; horizontal
flips double the geometry. The disparity channel is left as SGBM gives it (holes and all).
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch.nn import functional as F

from branchrange.core.segmentation.network_input import CLASSES, disparity_scale, network_input, padded_to_stride
from branchrange.learning.branchnet import BranchNet
from branchrange.learning.calibration import CALIBRATION_SEEDS
from branchrange.learning.resume import CHECKPOINT_NAME, restore_training_state, save_training_state
from branchrange.learning.samples import BRANCH, IGNORE, TRAIN_SEED_LIMIT, render_samples, training_sample
from stereo.weights import sha256_of

#: `BranchNetTrainConfig.domain`'s values and the scene domains (`samples.DOMAINS`) each trains and validates on
TRAINING_DOMAINS: dict[str, tuple[str, ...]] = {
    "generator": ("generator",),
    "randomized": ("randomized",),
    "mixed": ("generator", "randomized"),
}


@dataclass(frozen=True)
class BranchNetTrainConfig:
    """How `BranchNet` is trained (seeds are `stereo.synth` scene seeds).

    - `train_seeds`, `val_seeds`: [first, last) scene seeds for training and validation; both below
      `TRAIN_SEED_LIMIT`, disjoint, and the seeds trained on apart from the calibration's
      (`branchrange.learning.calibration.CALIBRATION_SEEDS`).
    - `steps`, `batch`, `crop`: optimiser steps, crops per step, crop side in px.
    - `lr`, `weight_decay`: AdamW with a cosine decay to 2 % of `lr`.
    - `class_weights`: cross-entropy weights of background, trunk, branch (branch pixels are ~1 %).
    - `branch_crop_share`: share of crops centred on a branch pixel (the rest anywhere).
    - `instance_balance`: branch pixels are weighted by (median branch area / their branch's area) to
      this power, clipped to 0.5–4×: recall counts branches, not pixels, and a thin stem of 40 px would
      otherwise weigh as little as one corner of a thick limb (0 = plain class weights).
    - `width`: `BranchNet` channel width; `seed`: crops, augmentation and initial weights;
      `threads`: torch CPU threads; `val_every`: steps between validations.
    - `init_weights`: a `branchnet.pt` of an earlier run (same width) to start from instead of random
      weights — a second stage; its SHA-256 is recorded in the metadata ("init_sha256"). Tensors whose
      name and shape match are taken; the rest (a full-resolution branch a stage adds, and the head that
      reads it) start from their random initial values.
    - `hardware_seeds`: [first, last) scene seeds rendered with orchard hardware (wires, posts, stakes, painted
      rods: `stereo.synth.hardware`), drawn from like the training seeds — a stage that teaches the network
      that a straight thin cylinder near the trunk is not always a branch; (0, 0) = none.
    - `fine_width`: channels of `BranchNet`'s full-resolution feature branch (0: none, the head reads
      the raw input).
    - `deep_blocks`: inverted residual blocks at each of the encoder's 1/4, 1/8 and 1/16 scales (`BranchNet`;
      0: none, the shipped network): capacity for a broad domain where pixels are few. `init_weights` of a
      network without them starts with the old network's output exactly (each block adds to its input a branch
      that starts at zero: `InvertedResidual`).
    - `domain`: where the training and validation scenes come from (`TRAINING_DOMAINS`): "generator", the
      `stereo.synth.render_scene` scenes the shipped model learnt, "randomized", the randomized domain
      (`samples.render_randomized_sample`, every factor drawn per scene: tree forms, bark, rows behind, ground,
      structures, seasons, light, sensor), whose seeds are a space of their own (cached under other names), or
      "mixed": both domains' scenes of `train_seeds` drawn alike (half the crops of each on average) and both
      domains' `val_seeds` validated together — breadth without forgetting the scenes the shipped figures are
      measured on; `hardware_seeds` are generator scenes, so none with "randomized".
    """

    train_seeds: tuple[int, int] = (1, 1201)
    val_seeds: tuple[int, int] = (2801, 2831)
    steps: int = 10000
    batch: int = 8
    crop: int = 192
    lr: float = 3e-3
    weight_decay: float = 1e-4
    class_weights: tuple[float, float, float] = (1.0, 1.0, 5.0)
    branch_crop_share: float = 0.6
    instance_balance: float = 0.0
    width: int = 12
    seed: int = 0
    threads: int = 2
    val_every: int = 500
    init_weights: str = ""
    fine_width: int = 0
    deep_blocks: int = 0
    hardware_seeds: tuple[int, int] = (0, 0)
    domain: str = "generator"

    def __post_init__(self) -> None:
        if self.domain not in TRAINING_DOMAINS:
            raise ValueError(f"domain must be one of {', '.join(TRAINING_DOMAINS)}, not {self.domain!r}")
        if self.domain == "randomized" and self.hardware_seeds != (0, 0):
            raise ValueError("hardware_seeds are generator scenes: the randomized domain draws its own structures")
        drawn_from = ["train_seeds"] + (["hardware_seeds"] if self.hardware_seeds != (0, 0) else [])
        for name in [*drawn_from, "val_seeds"]:
            first, last = getattr(self, name)
            if not 0 < first < last <= TRAIN_SEED_LIMIT:
                raise ValueError(f"{name} must be [first, last) with 0 < first < last ≤ {TRAIN_SEED_LIMIT}")
        for name in drawn_from:  # validation and calibration scenes are never trained on
            first, last = getattr(self, name)
            if max(first, self.val_seeds[0]) < min(last, self.val_seeds[1]):
                raise ValueError(f"{name} and val_seeds overlap")
            if max(first, CALIBRATION_SEEDS[0]) < min(last, CALIBRATION_SEEDS[1]):
                raise ValueError(
                    f"{name} overlap the calibration scenes {CALIBRATION_SEEDS[0]}–{CALIBRATION_SEEDS[1] - 1} "
                    "(a confidence measured on scenes trained on would be optimistic)"
                )
        if self.steps < 1 or self.batch < 1 or self.crop % 16 or self.crop < 64:
            raise ValueError("steps and batch must be ≥ 1 and crop a multiple of 16, ≥ 64")
        if not 0 <= self.fine_width <= 64:
            raise ValueError("fine_width must lie in [0, 64] (0 = no full-resolution branch)")
        if not 0 <= self.deep_blocks <= 4:
            raise ValueError("deep_blocks must lie in [0, 4] (0 = the shipped encoder)")
        if not 0 <= self.instance_balance <= 2:
            raise ValueError("instance_balance must lie in [0, 2] (an exponent; 0 = off)")


def augment(left: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """`uint8 H×W×3` with random gain, contrast, gamma, colour balance, greyscale, blur and noise."""
    image = left.astype(np.float32) / 255.0
    image = image * rng.uniform(0.85, 1.15, size=3)  # white balance
    mean = image.mean()
    image = (image - mean) * rng.uniform(0.6, 1.4) + mean * rng.uniform(0.5, 1.5)  # contrast, exposure
    image = np.clip(image, 0.0, 1.0) ** rng.uniform(0.6, 1.6)
    if rng.random() < 0.3:
        image = np.repeat(image.mean(axis=2, keepdims=True), 3, axis=2)
    if rng.random() < 0.3:
        image = cv2.GaussianBlur(image, (0, 0), rng.uniform(0.4, 1.3))
    image = image + rng.normal(0.0, rng.uniform(0.0, 0.025), size=image.shape).astype(np.float32)
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def instance_weights(classes: np.ndarray, instances: np.ndarray, power: float) -> np.ndarray:
    """`float32 H×W` pixel weights: (median branch area / own branch's area) ** `power` on branch pixels,
    clipped to 0.5–4, and 1 elsewhere (`classes`, `instances` as in a sample; see `instance_balance`)."""
    weights = np.ones(classes.shape, dtype=np.float32)
    branch = classes == BRANCH
    if power == 0 or not branch.any():
        return weights
    _, inverse, areas = np.unique(instances[branch], return_inverse=True, return_counts=True)
    factor = np.clip((np.median(areas) / areas) ** power, 0.5, 4.0).astype(np.float32)
    weights[branch] = factor[inverse]
    return weights


def training_crop(
    sample: dict[str, np.ndarray], config: BranchNetTrainConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(input `float32 (5, c, c)`, classes `int64 (c, c)`, pixel weights `float32 (c, c)`, see
    `instance_weights`) of one randomly scaled, augmented, cropped sample."""
    scale = float(rng.uniform(0.5, 1.6))
    height, width = sample["classes"].shape
    size = (max(config.crop, round(width * scale)), max(config.crop, round(height * scale)))
    left = cv2.resize(sample["left"], size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    disparity = cv2.resize(sample["disparity"].astype(np.float32), size, interpolation=cv2.INTER_NEAREST)
    classes = cv2.resize(sample["classes"], size, interpolation=cv2.INTER_NEAREST)
    weights = cv2.resize(
        instance_weights(sample["classes"], sample["instances"], config.instance_balance),
        size,
        interpolation=cv2.INTER_NEAREST,
    )
    branch_v, branch_u = np.nonzero(classes == BRANCH)
    half = config.crop // 2
    if len(branch_u) and rng.random() < config.branch_crop_share:
        pick = int(rng.integers(len(branch_u)))
        top = int(np.clip(branch_v[pick] - half + rng.integers(-half // 2, half // 2 + 1), 0, size[1] - config.crop))
        lft = int(np.clip(branch_u[pick] - half + rng.integers(-half // 2, half // 2 + 1), 0, size[0] - config.crop))
    else:
        top, lft = int(rng.integers(0, size[1] - config.crop + 1)), int(rng.integers(0, size[0] - config.crop + 1))
    window = np.s_[top : top + config.crop, lft : lft + config.crop]
    # the crop's disparity is scaled like its whole frame's, as at run time
    features = network_input(augment(left[window], rng), disparity[window], disparity_scale(disparity))
    target = classes[window].astype(np.int64)
    pixel_weights = weights[window]
    if rng.random() < 0.5:
        features, target, pixel_weights = features[:, :, ::-1], target[:, ::-1], pixel_weights[:, ::-1]
    return np.ascontiguousarray(features), np.ascontiguousarray(target), np.ascontiguousarray(pixel_weights)


def load_matching_weights(model: BranchNet, state: dict[str, torch.Tensor]) -> list[str]:
    """Load the tensors of `state` whose name and shape match `model`'s; the names of those left at their
    initial values (sorted). ValueError when `state` is of another width (not an earlier stage of this model)."""
    own = model.state_dict()
    stem = "stem.0.0.weight"  # (width, inputs, 3, 3)
    if stem not in state or state[stem].shape != own[stem].shape:
        found = tuple(state[stem].shape) if stem in state else "none"
        raise ValueError(f"init_weights: not a BranchNet of width {model.width} (its stem is {found})")
    matching = {name: value for name, value in state.items() if name in own and own[name].shape == value.shape}
    model.load_state_dict(matching, strict=False)
    return sorted(set(own) - set(matching))


def weighted_cross_entropy(
    logits: torch.Tensor, targets: torch.Tensor, class_weights: torch.Tensor, pixel_weights: torch.Tensor
) -> torch.Tensor:
    """Cross-entropy of `logits` (N, C, H, W) against `targets` (N, H, W; `IGNORE` left out), each pixel
    weighted by its class weight times its `pixel_weights` (N, H, W), normalised by the weights' sum
    (with pixel weights of 1 it equals `F.cross_entropy(weight=class_weights)`)."""
    counted = targets != IGNORE
    safe = torch.where(counted, targets, torch.zeros_like(targets))
    per_pixel = F.cross_entropy(logits, safe, reduction="none")
    weights = class_weights[safe] * pixel_weights * counted
    return (per_pixel * weights).sum() / weights.sum().clamp_min(1e-12)


def class_iou(model: BranchNet, samples: list[dict[str, np.ndarray]]) -> dict[str, float]:
    """Intersection over union per class on whole frames (IGNORE pixels left out)."""
    intersection = np.zeros(len(CLASSES))
    union = np.zeros(len(CLASSES))
    model.eval()
    with torch.inference_mode():
        for sample in samples:
            features, (h, w) = padded_to_stride(network_input(sample["left"], sample["disparity"].astype(np.float32)))
            predicted = model(torch.from_numpy(features)[None])[0].argmax(0).numpy()[:h, :w]
            truth = sample["classes"]
            counted = truth != IGNORE
            for k in range(len(CLASSES)):
                p, t = (predicted == k) & counted, (truth == k) & counted
                intersection[k] += np.count_nonzero(p & t)
                union[k] += np.count_nonzero(p | t)
    model.train()
    return {name: float(intersection[k] / union[k]) if union[k] else float("nan") for k, name in enumerate(CLASSES)}


def optimiser_step(loss: torch.Tensor, optimiser: torch.optim.Optimizer, schedule: Any) -> float:
    """One step down `loss`'s gradient, then one of the learning-rate `schedule`; the loss's value."""
    optimiser.zero_grad(set_to_none=True)
    loss.backward()
    optimiser.step()
    schedule.step()
    return float(loss.detach())


def export_onnx(model: BranchNet, path: Path) -> str:
    """Write `model` as ONNX (input `image` (1, 5, H, W), dynamic H, W; output `logits`); its SHA-256."""
    model = model.eval().to(memory_format=torch.contiguous_format)
    example = torch.zeros(1, 5, 368, 640)
    torch.onnx.export(
        model,
        example,
        str(path),
        input_names=["image"],
        output_names=["logits"],
        dynamic_axes={"image": {2: "height", 3: "width"}, "logits": {2: "height", 3: "width"}},
        opset_version=17,
        dynamo=False,
    )
    return sha256_of(path)


def train_branchnet(
    config: BranchNetTrainConfig, out_dir: Path, data_dir: Path, log=print, workers: int = 1, resume: bool = False
) -> dict:
    """Train, validate and export (see the module docstring); returns the metadata written to `branchnet.json`.
    The scenes not yet in `data_dir` are rendered first, in `workers` processes (`render_samples`). At every
    validation the run's whole state is saved to `out_dir`/`CHECKPOINT_NAME`; `resume` continues from it (same
    config: ValueError otherwise) and ends with the weights the run would have had uninterrupted."""
    from stereo.io import write_rgb
    from stereo.training.curves import plot_panel

    if config.init_weights and not Path(config.init_weights).is_file():
        raise ValueError(f"init_weights: no file {config.init_weights} (train the stage before this one first)")
    torch.manual_seed(config.seed)
    torch.set_num_threads(config.threads)
    rng = np.random.default_rng(config.seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    domains = TRAINING_DOMAINS[config.domain]
    train_seeds = [(s, False, domain) for domain in domains for s in range(*config.train_seeds)]
    train_seeds += [(s, True, "generator") for s in range(*config.hardware_seeds)]
    for domain in domains:
        scenes = [(s, h) for s, h, d in train_seeds if d == domain] + [(s, False) for s in range(*config.val_seeds)]
        rendered = render_samples(data_dir, scenes, workers, domain)
        if rendered:
            processes = f"{workers} process{'es' if workers > 1 else ''}"
            log(f"rendered {rendered} {domain} scenes into {data_dir} ({processes})")
    validation = [training_sample(data_dir, s, domain=domain) for domain in domains for s in range(*config.val_seeds)]
    model = BranchNet(config.width, config.fine_width, config.deep_blocks)
    init_sha256 = None
    if config.init_weights:
        init_sha256 = sha256_of(Path(config.init_weights))
        fresh = load_matching_weights(model, torch.load(config.init_weights, map_location="cpu", weights_only=True))
        if fresh:
            log(f"from {config.init_weights}: all but {len(fresh)} tensors ({', '.join(fresh)}), which start fresh")
    model = model.to(memory_format=torch.channels_last)  # ~1.4× faster convolutions on CPU
    optimiser = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    schedule = torch.optim.lr_scheduler.OneCycleLR(
        optimiser, max_lr=config.lr, total_steps=config.steps, pct_start=0.05, final_div_factor=50
    )
    weights = torch.tensor(config.class_weights, dtype=torch.float32)
    history: list[dict] = []
    done = 0
    checkpoint = out_dir / CHECKPOINT_NAME
    if resume:
        done, history = restore_training_state(checkpoint, asdict(config), model, optimiser, schedule, rng)
        log(f"resumed from {checkpoint} after step {done}")
    running, start = [], time.perf_counter()
    for step in range(done + 1, config.steps + 1):
        crops = []
        for _ in range(config.batch):
            seed, hardware, domain = train_seeds[int(rng.choice(len(train_seeds)))]  # np.arange's choice's draws
            sample = training_sample(data_dir, seed, hardware, domain)
            crops.append(training_crop(sample, config, rng))
        inputs = torch.from_numpy(np.stack([c[0] for c in crops])).contiguous(memory_format=torch.channels_last)
        targets = torch.from_numpy(np.stack([c[1] for c in crops]))
        logits = model(inputs)
        if config.instance_balance == 0:  # torch's own reduction: bit for bit the first stage as it was trained
            loss = F.cross_entropy(logits, targets, weight=weights, ignore_index=IGNORE)
        else:
            pixel_weights = torch.from_numpy(np.stack([c[2] for c in crops]))
            loss = weighted_cross_entropy(logits, targets, weights, pixel_weights)
        running.append(optimiser_step(loss, optimiser, schedule))
        if step % config.val_every == 0 or step == config.steps:
            iou = class_iou(model, validation)
            row = {
                "step": step,
                "train_loss": float(np.mean(running)),
                **{f"iou_{k}": v for k, v in iou.items()},
                "seconds": round(time.perf_counter() - start, 1),
            }
            history.append(row)
            torch.save(model.state_dict(), out_dir / "branchnet.pt")  # the newest weights, for a look before the end
            save_training_state(checkpoint, asdict(config), step, model, optimiser, schedule, rng, history)
            running = []
            log(" ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
    with (out_dir / "metrics.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(history[0]))
        writer.writeheader()
        writer.writerows(history)
    steps = [row["step"] for row in history]
    write_rgb(
        out_dir / "training_curve.png",
        np.concatenate(
            [
                plot_panel("train loss", steps, [r["train_loss"] for r in history], (31, 119, 180), "step"),
                plot_panel("val IoU branch", steps, [r["iou_branch"] for r in history], (214, 39, 40), "step"),
                plot_panel("val IoU trunk", steps, [r["iou_trunk"] for r in history], (44, 160, 44), "step"),
            ],
            axis=1,
        ),
    )
    sha256 = export_onnx(model, out_dir / "branchnet.onnx")
    meta = {
        "model": "BranchNet",
        "width": config.width,
        "fine_width": config.fine_width,
        "deep_blocks": config.deep_blocks,
        "classes": list(CLASSES),
        "onnx_sha256": sha256,
        "config": asdict(config),
        "final": history[-1],
        "torch": torch.__version__,
        **({"init_sha256": init_sha256} if init_sha256 else {}),
    }
    (out_dir / "branchnet.json").write_text(json.dumps(meta, indent=1) + "\n")
    return meta
