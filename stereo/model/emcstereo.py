"""EMCStereo: the four stages (features, cost volume, aggregation, regression) put together."""
from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from .aggregation import StackedHourglass
from .backbone import FeatureBackbone
from .cost_volume import concat_cost_volume
from .fast_inference import FastInference
from .regression import DisparityRegression, upsample_cost

#: The smallest padded H and W the network accepts (the 64×64 SPP pool at ¼ resolution).
MIN_SIZE = 256
#: H and W must be multiples of this (two stride-2 3D stages below ¼ resolution).
SIZE_MULTIPLE = 32


@dataclass(frozen=True)
class ModelConfig:
    """What identifies an EMCStereo variant; stored in our checkpoints."""

    ema: bool = True
    msf: bool = True
    coord: bool = True
    max_disp: int = 192

    def to_dict(self) -> dict[str, bool | int]:
        return asdict(self)


class EMCStereo(nn.Module):
    """EMCStereo (PSMNet template + EMA, MSFblock, CoordAtt); any of the eight variants.

    `forward(left, right)`: ImageNet-normalised (B, 3, H, W) tensors, H and W multiples of 32 and
    ≥ 256. Training mode returns the three deeply supervised disparities [(B, H, W)] × 3; eval
    mode returns only the third, (B, H, W), in pixels of the input.
    """

    def __init__(self, ema: bool = True, msf: bool = True, coord: bool = True, max_disp: int = 192) -> None:
        super().__init__()
        if max_disp <= 0 or max_disp % 4:
            raise ValueError(f"max_disp must be a positive multiple of 4, got {max_disp}")
        self.config = ModelConfig(ema, msf, coord, max_disp)
        self.backbone = FeatureBackbone(ema=ema, msf=msf, coord=coord)
        self.aggregation = StackedHourglass()
        self.regression = DisparityRegression(max_disp)

    @property
    def max_disp(self) -> int:
        return self.config.max_disp

    def forward(self, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor | list[torch.Tensor]:
        costs = self._costs(left, right, self.max_disp)
        height, width = left.shape[2:]
        if self.training:
            return [self.regression(self._upsample(c, self.max_disp, height, width)) for c in costs]
        return self.regression(self._upsample(costs[-1], self.max_disp, height, width))

    def infer(self, left: torch.Tensor, right: torch.Tensor, max_disp: int | None = None,
              *, fast: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Disparity and soft-argmin confidence, both (B, H, W), over a search range ≤ max_disp.

        A smaller `max_disp` (a multiple of 4) for a known working range shrinks the cost volume
        and the 3D work in proportion; the disparity scale stays the one the model was trained with.
        `fast` (the default) runs `FastInference`, an inference-only copy with BatchNorm folded,
        channels-last layouts and a row-chunked soft-argmin: the eval-mode result (running BN
        statistics) whatever mode this model is in, equal to `fast=False` in eval mode up to float
        rounding. `fast=False` runs this module's own layers, the reference for parity.
        """
        disparities = self.max_disp if max_disp is None else max_disp
        if disparities <= 0 or disparities % 4 or disparities > self.max_disp:
            raise ValueError(f"inference max_disp must be a multiple of 4 in (0, {self.max_disp}], got {max_disp}")
        if fast:
            check_input_size(left, right)
            with torch.inference_mode():
                return self.fast_inference()(left, right, disparities)
        cost = self._costs(left, right, disparities)[-1]
        height, width = left.shape[2:]
        return self.regression.with_confidence(self._upsample(cost, disparities, height, width))

    def fast_inference(self) -> FastInference:
        """The `FastInference` copy of the current weights, rebuilt when any parameter or buffer changed.

        A change is seen through each tensor's storage address and in-place version counter
        (`load_state_dict`, optimiser steps and `.to(device)` all move one of them).
        """
        fingerprint = tuple((t.data_ptr(), t._version, t.dtype, t.device)
                            for t in self.state_dict(keep_vars=True).values())
        cached = self.__dict__.get("_fast_cache")
        if cached is None or cached[0] != fingerprint:
            cached = (fingerprint, FastInference(self))
            # A plain attribute, not a submodule: the copy must stay out of state_dict and parameters().
            self.__dict__["_fast_cache"] = cached
        return cached[1]

    def _costs(self, left: torch.Tensor, right: torch.Tensor, disparities: int) -> list[torch.Tensor]:
        check_input_size(left, right)
        features = self.backbone(torch.cat([left, right], dim=0))
        ref, tgt = features.chunk(2, dim=0)
        volume = concat_cost_volume(ref, tgt, disparities // 4)
        return self.aggregation(volume)

    def _upsample(self, cost: torch.Tensor, disparities: int, height: int, width: int) -> torch.Tensor:
        depth_step = (self.max_disp // 4 - 1) / (self.max_disp - 1)
        return upsample_cost(cost, disparities, height, width, depth_step)


def check_input_size(left: torch.Tensor, right: torch.Tensor) -> None:
    """Raise a ValueError naming the shape when the pair cannot go through the network."""
    if left.shape != right.shape or left.dim() != 4 or left.shape[1] != 3:
        raise ValueError(f"left and right must both be (B, 3, H, W); got {tuple(left.shape)} and {tuple(right.shape)}")
    height, width = left.shape[2:]
    if height % SIZE_MULTIPLE or width % SIZE_MULTIPLE or height < MIN_SIZE or width < MIN_SIZE:
        raise ValueError(
            f"input {height}×{width} must be padded to multiples of {SIZE_MULTIPLE} and at least "
            f"{MIN_SIZE}×{MIN_SIZE} (use stereo.padding)"
        )
