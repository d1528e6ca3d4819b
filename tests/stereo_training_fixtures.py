"""Builders shared by the dataset, training, evaluation, DDP and self-supervision tests.

- `planar_scene`: a textured stereo pair with exact disparity — a slanted background plane, nearer
  fronto-parallel boxes and a sky band without depth; the left view is the right view resampled
  at x − d, so the ground truth is exact wherever nothing is occluded.
- `write_virtualtree_layout`: such scenes written as VirtualTree files (PNG images, EXR depth in
  cm with sky at 65504, six-token split files), the format the real loader reads.
- `one_thread`: an autouse fixture for the modules that import it (one torch thread);
  `single_torch_thread` the same as a context manager, for module-scoped fixtures.
- `TinyStereoNet`: a small correlation + soft-argmin network with EMCStereo's forward contract
  (three disparities in training mode, the last in eval mode), for tests whose subject is the
  training machinery (DDP, self-supervision) and not the network.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from stereo.datasets.virtualtree import VIRTUALTREE_BASELINE_CM, VIRTUALTREE_FOCAL_PX
from stereo.io import write_exr_depth, write_rgb

SKY_CM = 65504.0


@contextmanager
def single_torch_thread() -> Iterator[None]:
    """Run the body on one torch thread (module-scoped fixtures use it: they start before `one_thread`)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@pytest.fixture(autouse=True)
def one_thread():
    """Run a test on one torch thread: on a shared 2-core machine that is several times faster and deterministic."""
    with single_torch_thread():
        yield


@dataclass
class Scene:
    """A stereo pair (RGB uint8) with its left disparity (px, 0 = sky)."""

    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray


def _texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Colour texture with coarse and fine structure (float32 in [0, 1])."""
    coarse = cv2.resize(
        rng.random((height // 8 + 1, width // 8 + 1, 3)).astype(np.float32),
        (width, height),
        interpolation=cv2.INTER_CUBIC,
    )
    fine = cv2.GaussianBlur(rng.random((height, width, 3)).astype(np.float32), (0, 0), 0.8)
    return np.clip(0.55 * coarse + 0.45 * fine, 0.0, 1.0)


def planar_scene(
    seed: int, height: int, width: int, disp_range: tuple[float, float] = (4.0, 40.0), sky_rows: int = 16
) -> Scene:
    """A random planar scene of `height × width` px with disparities inside `disp_range`."""
    rng = np.random.default_rng(seed)
    lo, hi = disp_range
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    base = rng.uniform(lo, lo + 0.4 * (hi - lo))
    disparity = base + rng.uniform(-0.2, 0.2) * (hi - lo) * xs / width + rng.uniform(0, 0.2) * (hi - lo) * ys / height
    for _ in range(2):
        h, w = int(rng.integers(height // 5, height // 2)), int(rng.integers(width // 6, width // 3))
        top, left = int(rng.integers(sky_rows, height - h)), int(rng.integers(0, width - w))
        disparity[top : top + h, left : left + w] = rng.uniform(lo + 0.5 * (hi - lo), hi)
    disparity = np.clip(disparity, lo, hi).astype(np.float32)
    disparity[:sky_rows] = 0.0
    right = _texture(rng, height, width)
    left = cv2.remap(right, xs - disparity, ys, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    to_u8 = lambda a: np.round(np.clip(a, 0, 1) * 255).astype(np.uint8)  # noqa: E731
    return Scene(to_u8(left), to_u8(right), disparity)


def write_virtualtree_layout(
    root: Path,
    scenes: Sequence[Scene],
    splits: dict[str, Sequence[int]],
    focal_px: float = VIRTUALTREE_FOCAL_PX,
    baseline_cm: float = VIRTUALTREE_BASELINE_CM,
) -> Path:
    """Write scenes as `left image/left_N.png`, `right image/right_N.png`, `left depth/depth_N.exr` (cm) + splits."""
    for folder in ("left image", "right image", "left depth"):
        (root / folder).mkdir(parents=True, exist_ok=True)
    for n, scene in enumerate(scenes):
        write_rgb(root / "left image" / f"left_{n}.png", scene.left)
        write_rgb(root / "right image" / f"right_{n}.png", scene.right)
        depth = np.full(scene.disparity.shape, SKY_CM, dtype=np.float32)
        valid = scene.disparity > 0
        depth[valid] = focal_px * baseline_cm / scene.disparity[valid]
        write_exr_depth(root / "left depth" / f"depth_{n}.exr", depth, pixel_type="half")
    for name, indices in splits.items():
        lines = [f"left image/left_{n}.png left depth/depth_{n}.exr right image/right_{n}.png" for n in indices]
        (root / f"{name}.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return root


class TinyStereoNet(nn.Module):
    """Stride-2 features → correlation over `max_disp/2` shifts → three residual heads → soft-argmin ×2."""

    def __init__(self, max_disp: int = 48, channels: int = 16) -> None:
        super().__init__()
        self.max_disp = max_disp
        self.shifts = max_disp // 2
        self.features = nn.Sequential(
            nn.Conv2d(3, channels, 3, stride=2, padding=1),
            nn.BatchNorm2d(channels),
            nn.ReLU(),
            nn.Conv2d(channels, channels, 3, padding=1),
        )
        self.heads = nn.ModuleList(nn.Conv2d(self.shifts, self.shifts, 3, padding=1) for _ in range(3))
        self.register_buffer("disparities", 2.0 * torch.arange(self.shifts, dtype=torch.float32).view(1, -1, 1, 1))

    def _correlation(self, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
        volume = left.new_zeros(left.shape[0], self.shifts, *left.shape[2:])
        volume[:, 0] = (left * right).mean(1)
        for d in range(1, self.shifts):
            volume[:, d, :, d:] = (left[..., d:] * right[..., :-d]).mean(1)
        return volume

    def forward(self, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor | list[torch.Tensor]:
        cost = self._correlation(self.features(left), self.features(right))
        outputs, current = [], cost
        for head in self.heads:
            current = current + head(current)
            full = F.interpolate(current, size=left.shape[2:], mode="bilinear", align_corners=False)
            outputs.append((F.softmax(full, dim=1) * self.disparities).sum(1))
        return outputs if self.training else outputs[-1]
