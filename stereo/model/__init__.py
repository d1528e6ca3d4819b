"""The EMCStereo network, split into the stages every stereo paper draws."""

from .emcstereo import EMCStereo, ModelConfig
from .stages import MIN_SIZE, SIZE_MULTIPLE

__all__ = ["EMCStereo", "ModelConfig", "MIN_SIZE", "SIZE_MULTIPLE"]
