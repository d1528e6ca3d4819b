"""The EMCStereo network, split into the stages every stereo paper draws."""
from .emcstereo import MIN_SIZE, SIZE_MULTIPLE, EMCStereo, ModelConfig

__all__ = ["EMCStereo", "ModelConfig", "MIN_SIZE", "SIZE_MULTIPLE"]
