"""The order of EMCStereo's stages, written once: features → cost volume → aggregation → regression.

`StagedStereo` runs the sequence; a subclass says only how each stage is computed. `EMCStereo`
(the trainable reference) and `FastInference` (folded, fused, channels-last) are the two
implementations, so a change to the sequence is made here and both follow it.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Iterator

import torch
from torch import nn

#: The smallest padded H and W the network accepts (the 64×64 SPP pool at ¼ resolution).
MIN_SIZE = 256
#: H and W must be multiples of this (two stride-2 3D stages below ¼ resolution).
SIZE_MULTIPLE = 32


class StagedStereo(nn.Module, ABC):
    """The stage sequence of a PSMNet-style network; subclasses implement the four stages.

    Stages, all on ImageNet-normalised (B, 3, H, W) views padded as `check_input_size` asks:
    `features` → two (B, C, H/4, W/4) feature maps; `cost_volume` → (B, 2C, D/4, H/4, W/4);
    `aggregate` → the deeply supervised costs c1, c2, c3, each (B, 1, D/4, H/4, W/4), yielded in
    turn so that a consumer keeping only the last holds one at a time; `regress` → disparity and
    confidence, both (B, H, W), disparity in pixels of the input.
    """

    @abstractmethod
    def features(self, left: torch.Tensor, right: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Reference and target feature maps, each (B, C, H/4, W/4)."""

    @abstractmethod
    def cost_volume(self, reference: torch.Tensor, target: torch.Tensor, disparities: int) -> torch.Tensor:
        """The (B, 2C, disparities/4, H/4, W/4) concatenation volume of the two feature maps."""

    @abstractmethod
    def aggregate(self, volume: torch.Tensor) -> Iterator[torch.Tensor]:
        """Yield the costs c1, c2, c3 (B, 1, D/4, H/4, W/4); the caller lets go of `volume`."""

    @abstractmethod
    def regress(
        self, cost: torch.Tensor, disparities: int, height: int, width: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Disparity (px) and confidence, both (B, height, width), from one low-resolution cost."""

    def costs(self, left: torch.Tensor, right: torch.Tensor, disparities: int) -> Iterator[torch.Tensor]:
        """The first three stages: yield c1, c2, c3 (B, 1, disparities/4, H/4, W/4) for a padded pair.

        The features and the volume are passed straight on, never bound to a name here, so each
        is freed as soon as the stage that reads it lets go of it (the volume is the largest tensor).
        """
        check_input_size(left, right)
        yield from self.aggregate(self.cost_volume(*self.features(left, right), disparities))

    def disparity_and_confidence(
        self, left: torch.Tensor, right: torch.Tensor, disparities: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The whole sequence at inference: disparity and confidence (B, H, W) from the last cost."""
        height, width = left.shape[2:]
        return self.regress(last_cost(self.costs(left, right, disparities)), disparities, height, width)


def last_cost(costs: Iterator[torch.Tensor]) -> torch.Tensor:
    """The last of the aggregation's costs, holding one at a time (a list would keep c1 and c2 alive)."""
    return deque(costs, maxlen=1).pop()


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
