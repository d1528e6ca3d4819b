"""The fast inference path: an inference-only copy of EMCStereo that computes the same disparities.

It runs the model's own stage sequence (`stages.StagedStereo`) and swaps only how each stage is
computed. What it changes against the plain eval forward, all exact up to float rounding:
- BatchNorm folded into the convolution before it (`fusion.fold_batchnorms`), on a copy;
- convolutions as direct oneDNN calls with the ReLU fused in (`onednn.fuse_convolutions`);
- channels-last layouts (NHWC / NDHWC), on which oneDNN's convolutions run several times faster
  on CPU than on NCHW / NCDHW (measured in `benchmarks/RESULTS.md`);
- the cost volume written straight into a channels-last tensor;
- hourglass outputs dropped as soon as the third head no longer needs them, and the heap the 2D
  backbone freed handed back before the 3D volumes are allocated (`memory.release_freed_memory`);
- the trilinear upsampling fused with the soft-argmin, a few rows at a time, so the
  full-resolution (D, H, W) volume never exists.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Protocol

import torch

from .cost_volume import concat_cost_volume
from .fusion import fold_batchnorms
from .memory import release_freed_memory
from .onednn import fuse_convolutions
from .regression import upsampled_soft_argmin
from .stages import StagedStereo


class _Wiring(Protocol):
    @property
    def align_corners(self) -> bool: ...


class TrainedStereo(Protocol):
    """What `FastInference` copies from a trained model: `stereo.model.emcstereo.EMCStereo` has it all (EMCStereo
    builds its own fast copy, so this module names what it reads rather than importing the model)."""

    max_disp: int
    backbone: torch.nn.Module
    aggregation: torch.nn.Module
    regression: torch.nn.Module

    @property
    def config(self) -> _Wiring: ...


class FastInference(StagedStereo):
    """Eval-mode EMCStereo (running BN statistics) for inference only; built from a model, never trained.

    `forward(left, right, disparities) -> (disparity, confidence)`, both (B, H, W) float32;
    inputs as for `EMCStereo.forward`, `disparities` a multiple of 16 ≤ the model's `max_disp`.
    `use_onednn=False` keeps PyTorch's public convolution calls (what runs on CUDA anyway).
    """

    def __init__(self, model: TrainedStereo, rows_per_chunk: int = 32, use_onednn: bool = True) -> None:
        super().__init__()
        values = model.regression.weight.detach().reshape(-1)
        if not torch.equal(values, torch.arange(values.numel(), dtype=values.dtype, device=values.device)):
            raise ValueError("the soft-argmin weights (regression.weight) must be 0, 1, …, max_disp−1")
        self.max_disp = model.max_disp
        self.align_corners = model.config.align_corners  # the wiring travels inside the aggregation copy
        self.rows_per_chunk = rows_per_chunk
        self.backbone = fuse_convolutions(fold_batchnorms(model.backbone), use_onednn)
        self.aggregation = fuse_convolutions(fold_batchnorms(model.aggregation), use_onednn)
        self.register_buffer("disparity_values", values.float().clone())
        self.requires_grad_(False)
        self.eval()

    def forward(self, left: torch.Tensor, right: torch.Tensor, disparities: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.disparity_and_confidence(left, right, disparities)

    def features(self, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Both views in one channels-last batch; the backbone's freed heap goes back before the 3D stages."""
        images = torch.cat([left, right], dim=0).contiguous(memory_format=torch.channels_last)
        reference, target = self.backbone(images).chunk(2, dim=0)
        del images
        release_freed_memory()
        return reference, target

    def cost_volume(self, reference: torch.Tensor, target: torch.Tensor, disparities: int) -> torch.Tensor:
        return concat_cost_volume(reference, target, disparities // 4, memory_format=torch.channels_last_3d)

    def aggregate(self, volume: torch.Tensor) -> Iterator[torch.Tensor]:
        return self.aggregation.costs(volume)

    def regress(
        self, cost: torch.Tensor, disparities: int, height: int, width: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Upsampling fused with the soft-argmin, `rows_per_chunk` output rows at a time."""
        return upsampled_soft_argmin(
            cost,
            self.disparity_values[:disparities],
            height,
            width,
            self.max_disp,
            self.align_corners,
            rows_per_chunk=self.rows_per_chunk,
        )
