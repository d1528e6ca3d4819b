"""Training and evaluation transforms of stereo samples, as in the paper's recipe.

Training: a random crop (256×512; 288×576 for SceneFlow) that prefers crops with valid
disparity, an asymmetric colour jitter (brightness, contrast, saturation 0.4, hue 0.5/π ≈ 0.159;
with probability 0.2 each view jittered on its own, otherwise both as one image), then ImageNet
normalisation. Evaluation: normalisation only (padding happens in `stereo.evaluation`). No flips,
no scaling.

Randomness comes from a `numpy.random.Generator` that `Augmented` derives from (seed, epoch,
sample index), so a resumed run sees exactly the augmentations the interrupted one would have.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)

Sample = dict[str, Any]


def random_valid_crop(
    sample: Sample,
    height: int,
    width: int,
    rng: np.random.Generator,
    *,
    max_disp: float = 192.0,
    tries: int = 20,
    enough_valid: int = 1024,
) -> Sample:
    """Crop `height×width` at random, keeping the try with most valid pixels (0 < d < max_disp).

    Up to `tries` positions are drawn; drawing stops at the first with ≥ `enough_valid` valid
    pixels. A sample smaller than the crop is returned uncropped.
    """
    full_h, full_w = sample["disparity"].shape
    if full_h < height or full_w < width:
        return sample
    disparity = sample["disparity"]
    best, best_valid = (0, 0), -1
    for _ in range(tries):
        top = int(rng.integers(0, full_h - height + 1))
        left = int(rng.integers(0, full_w - width + 1))
        window = disparity[top : top + height, left : left + width]
        valid = int(np.count_nonzero((window > 0) & (window < max_disp)))
        if valid > best_valid:
            best, best_valid = (top, left), valid
        if valid >= enough_valid:
            break
    top, left = best
    out = dict(sample)
    for key in ("left", "right", "disparity"):
        out[key] = np.ascontiguousarray(sample[key][top : top + height, left : left + width])
    return out


def _blend(image: np.ndarray, other: np.ndarray | float, factor: float) -> np.ndarray:
    """`factor·image + (1−factor)·other`, clipped to [0, 1]."""
    return np.clip(factor * image + (1.0 - factor) * other, 0.0, 1.0)


@dataclass(frozen=True)
class AsymmetricColorJitter:
    """Colour jitter of a stereo pair: one draw for both views, or with `asymmetric_prob` one per view."""

    brightness: float = 0.4
    contrast: float = 0.4
    saturation: float = 0.4
    hue: float = 0.5 / 3.14
    asymmetric_prob: float = 0.2

    def jitter(self, image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """One random jitter of an RGB `uint8` `H×W×3` image, the four adjustments in random order."""
        out = image.astype(np.float32) / 255.0
        for op in rng.permutation(4):
            if op == 0:
                out = _blend(out, 0.0, rng.uniform(max(0.0, 1 - self.brightness), 1 + self.brightness))
            elif op == 1:
                mean = float((out @ _LUMA).mean())
                out = _blend(out, mean, rng.uniform(max(0.0, 1 - self.contrast), 1 + self.contrast))
            elif op == 2:
                grey = (out @ _LUMA)[..., None]
                out = _blend(out, grey, rng.uniform(max(0.0, 1 - self.saturation), 1 + self.saturation))
            else:
                hsv = cv2.cvtColor(out, cv2.COLOR_RGB2HSV)  # float input: H in degrees [0, 360)
                hsv[..., 0] = np.mod(hsv[..., 0] + 360.0 * rng.uniform(-self.hue, self.hue), 360.0)
                out = np.clip(cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB), 0.0, 1.0)
        return np.round(out * 255.0).astype(np.uint8)

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        """The sample with jittered `left` and `right`; disparity untouched."""
        out = dict(sample)
        if rng.random() < self.asymmetric_prob:
            out["left"] = self.jitter(sample["left"], rng)
            out["right"] = self.jitter(sample["right"], rng)
        else:
            height = sample["left"].shape[0]
            both = self.jitter(np.concatenate([sample["left"], sample["right"]], axis=0), rng)
            out["left"], out["right"] = both[:height], both[height:]
        return out


def normalize_image(image: np.ndarray) -> torch.Tensor:
    """RGB `uint8` `H×W×3` → ImageNet-normalised float32 tensor `(3, H, W)`."""
    tensor = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float().div_(255.0)
    mean = torch.tensor(IMAGENET_MEAN).view(3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(3, 1, 1)
    return (tensor - mean) / std


def to_network_input(sample: Sample) -> Sample:
    """Images normalised to `(3,H,W)` tensors and disparity to a `(H,W)` float32 tensor; meta kept."""
    out = dict(sample)
    out["left"] = normalize_image(sample["left"])
    out["right"] = normalize_image(sample["right"])
    out["disparity"] = torch.from_numpy(np.ascontiguousarray(sample["disparity"], dtype=np.float32))
    return out


@dataclass(frozen=True)
class TrainTransform:
    """Crop preferring valid disparity, optional asymmetric colour jitter, normalisation."""

    crop_height: int = 256
    crop_width: int = 512
    color_jitter: AsymmetricColorJitter | None = AsymmetricColorJitter()
    max_disp: float = 192.0

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        sample = random_valid_crop(sample, self.crop_height, self.crop_width, rng, max_disp=self.max_disp)
        if self.color_jitter is not None:
            sample = self.color_jitter(sample, rng)
        return to_network_input(sample)


def eval_transform(sample: Sample, rng: np.random.Generator | None = None) -> Sample:
    """Evaluation: normalisation only, full resolution (the evaluator pads and un-pads)."""
    return to_network_input(sample)


class Augmented(Dataset):
    """A raw-sample dataset with a transform whose randomness depends only on (seed, epoch, index)."""

    def __init__(
        self,
        dataset: Dataset,
        transform: Callable[[Sample, np.random.Generator], Sample],
        seed: int = 0,
    ) -> None:
        self.dataset = dataset
        self.transform = transform
        self.seed = seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Select the augmentation draws of `epoch` (call before creating the epoch's DataLoader iterator)."""
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int) -> Sample:
        rng = np.random.default_rng([self.seed, self.epoch, index])
        return self.transform(self.dataset[index], rng)
