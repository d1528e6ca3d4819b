"""stereo: the EMCStereo network, its datasets, training, evaluation and inference backends."""
from .checkpoints import CheckpointError, load_model, save_checkpoint
from .model import EMCStereo, ModelConfig

__all__ = ["EMCStereo", "ModelConfig", "CheckpointError", "load_model", "save_checkpoint"]
