"""EMCStereo: the four stages (features, cost volume, aggregation, regression) put together."""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch

from .aggregation import StackedHourglass
from .backbone import SPP_POOLS, FeatureBackbone
from .cost_volume import concat_cost_volume
from .fast_inference import FastInference
from .regression import DisparityRegression, upsample_cost
from .stages import StagedStereo, check_input_size, last_cost

#: The largest disparity range a model may be built with: 5× the authors' 192, far above any camera
#: here, and small enough that a corrupt checkpoint cannot ask for a multi-gigabyte cost volume.
MAX_DISP_LIMIT = 1024
#: max_disp must be a multiple of this: the cost volume is at 1/4 resolution and each hourglass halves it twice.
DISPARITY_STEP = 16
#: Which skip the third hourglass gets: PSMNet's code feeds it `pre1`, OpenStereo's PSMNet cost
#: processor (on which the authors' EMCStereo is built) feeds it `pre2`.
HOURGLASS_WIRINGS = ("psmnet", "openstereo")


@dataclass(frozen=True)
class ModelConfig:
    """What identifies an EMCStereo variant and how its layers are wired; stored in our checkpoints.

    The defaults are the authors' EMCStereo: all three modules, 192 disparities, the third
    hourglass fed `pre2` (`hourglass_wiring="openstereo"`) and `align_corners=True` in the
    disparity upsampling. PSMNet's own code is `hourglass_wiring="psmnet"` (`pre1`) and, on
    PyTorch ≥ 0.4.1, `align_corners=False` (its `F.upsample` call leaves the default).
    """

    ema: bool = True
    msf: bool = True
    coord: bool = True
    max_disp: int = 192
    hourglass_wiring: str = "openstereo"
    align_corners: bool = True

    def __post_init__(self) -> None:
        for name in ("ema", "msf", "coord", "align_corners"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")
        max_disp = self.max_disp
        if (
            isinstance(max_disp, bool)
            or not isinstance(max_disp, int)
            or not 0 < max_disp <= MAX_DISP_LIMIT
            or max_disp % DISPARITY_STEP
        ):
            raise ValueError(
                f"max_disp must be a positive multiple of {DISPARITY_STEP} up to {MAX_DISP_LIMIT}, got {max_disp!r}"
            )
        if self.hourglass_wiring not in HOURGLASS_WIRINGS:
            raise ValueError(
                f"hourglass_wiring must be one of {', '.join(HOURGLASS_WIRINGS)}, got {self.hourglass_wiring!r}"
            )

    def to_dict(self) -> dict[str, bool | int | str]:
        return asdict(self)

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], defaults: Mapping[str, Any] = {}) -> ModelConfig:
        """Build from a stored dict, `defaults` filling absent keys; ValueError names an unknown key or bad value."""
        known = [f.name for f in fields(cls)]
        unknown = sorted(str(k) for k in values if k not in known)
        if unknown:
            raise ValueError(f"unknown model setting(s) {', '.join(map(repr, unknown))}; known: {', '.join(known)}")
        return cls(**{**defaults, **values})


class EMCStereo(StagedStereo):
    """EMCStereo (PSMNet template + EMA, MSFblock, CoordAtt); any of the eight variants.

    `forward(left, right)`: ImageNet-normalised (B, 3, H, W) tensors, H and W multiples of 32 and
    ≥ 256. Training mode returns the three deeply supervised disparities [(B, H, W)] × 3; eval
    mode returns only the third, (B, H, W), in pixels of the input. `hourglass_wiring` and
    `align_corners` are described in `ModelConfig`; a checkpoint must run with the ones it was trained with.
    The order of the stages is `StagedStereo`'s; this class gives the reference implementation of each.
    """

    def __init__(
        self,
        ema: bool = True,
        msf: bool = True,
        coord: bool = True,
        max_disp: int = 192,
        hourglass_wiring: str = "openstereo",
        align_corners: bool = True,
    ) -> None:
        super().__init__()
        self.config = ModelConfig(ema, msf, coord, max_disp, hourglass_wiring, align_corners)
        self.backbone = FeatureBackbone(ema=ema, msf=msf, coord=coord)
        self.aggregation = StackedHourglass(hourglass_wiring)
        self.regression = DisparityRegression(max_disp)

    @classmethod
    def from_config(cls, config: ModelConfig) -> EMCStereo:
        """The variant `config` describes, with freshly initialised weights."""
        return cls(config.ema, config.msf, config.coord, config.max_disp, config.hourglass_wiring, config.align_corners)

    @property
    def max_disp(self) -> int:
        return self.config.max_disp

    def forward(self, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor | list[torch.Tensor]:
        costs = self.costs(left, right, self.max_disp)
        height, width = left.shape[2:]
        if self.training:
            return [self.regression(self._upsample(c, self.max_disp, height, width)) for c in costs]
        return self.regression(self._upsample(last_cost(costs), self.max_disp, height, width))

    def infer(
        self, left: torch.Tensor, right: torch.Tensor, max_disp: int | None = None, *, fast: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Disparity and soft-argmin confidence, both (B, H, W), over a search range ≤ max_disp.

        A smaller `max_disp` (a multiple of 16) for a known working range shrinks the cost volume
        and the 3D work in proportion; the disparity scale stays the one the model was trained with.
        `fast` (the default) runs `FastInference`, an inference-only copy with BatchNorm folded,
        channels-last layouts and a row-chunked soft-argmin: the eval-mode result (running BN
        statistics) whatever mode this model is in, equal to `fast=False` in eval mode up to float
        rounding. `fast=False` runs this module's own layers, the reference for parity.
        """
        disparities = self.max_disp if max_disp is None else max_disp
        if disparities <= 0 or disparities % DISPARITY_STEP or disparities > self.max_disp:
            raise ValueError(
                f"inference max_disp must be a multiple of {DISPARITY_STEP} in (0, {self.max_disp}], got {max_disp}"
            )
        if fast:
            check_input_size(left, right)  # before building the fast copy, not only inside it
            with torch.inference_mode():
                return self.fast_inference()(left, right, disparities)
        return self.disparity_and_confidence(left, right, disparities)

    def fast_inference(self) -> FastInference:
        """The `FastInference` copy of the current weights, rebuilt when any parameter or buffer changed.

        A change is seen through each tensor's storage address and in-place version counter
        (`load_state_dict`, optimiser steps and `.to(device)` all move one of them).
        """
        fingerprint = tuple(
            (t.data_ptr(), t._version, t.dtype, t.device) for t in self.state_dict(keep_vars=True).values()
        )
        cached = self.__dict__.get("_fast_cache")
        if cached is None or cached[0] != fingerprint:
            cached = (fingerprint, FastInference(self))
            # A plain attribute, not a submodule: the copy must stay out of state_dict and parameters().
            self.__dict__["_fast_cache"] = cached
        return cached[1]

    def features(self, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.training and per_view_batchnorm_possible(left):
            # One view at a time, as PSMNet and the authors do: each BatchNorm normalises (and
            # updates its running statistics) with one view's batch statistics, twice per step.
            return self.backbone(left), self.backbone(right)
        # eval (running statistics: one batched pass is the same, and faster) or the fallback
        reference, target = self.backbone(torch.cat([left, right], dim=0)).chunk(2, dim=0)
        return reference, target

    def cost_volume(self, reference: torch.Tensor, target: torch.Tensor, disparities: int) -> torch.Tensor:
        return concat_cost_volume(reference, target, disparities // 4)

    def aggregate(self, volume: torch.Tensor) -> Iterator[torch.Tensor]:
        return self.aggregation.costs(volume)

    def regress(
        self, cost: torch.Tensor, disparities: int, height: int, width: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return self.regression.with_confidence(self._upsample(cost, disparities, height, width))

    def _upsample(self, cost: torch.Tensor, disparities: int, height: int, width: int) -> torch.Tensor:
        return upsample_cost(cost, disparities, height, width, self.max_disp, self.config.align_corners)


def per_view_batchnorm_possible(view: torch.Tensor) -> bool:
    """Whether a training batch of one view (B, 3, H, W) leaves BatchNorm more than one value per channel.

    The coarsest SPP branch pools ¼-resolution features 64×64: at batch 1 with H and W < 512 that
    is a single value, which BatchNorm refuses in training (the reference code fails there). Then
    both views go through together, as one batch of 2, and a warning says so once per process.
    """
    batch, _, height, width = view.shape
    pool = SPP_POOLS[0]
    if batch * (height // 4 // pool) * (width // 4 // pool) > 1:
        return True
    if not _FALLBACK_WARNED:
        _FALLBACK_WARNED.append(True)
        warnings.warn(
            f"training batch 1 at {height}×{width}: BatchNorm statistics span both views (per-view "
            "needs a batch ≥ 2 or a crop ≥ 512 on one side)",
            stacklevel=3,
        )
    return False


#: Set once the per-view fallback has been reported (one warning per process, not per step).
_FALLBACK_WARNED: list[bool] = []
