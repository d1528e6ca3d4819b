"""stereo: the EMCStereo network, its datasets, training, evaluation and inference backends."""
from .model import EMCStereo, ModelConfig

__all__ = ["EMCStereo", "ModelConfig"]
