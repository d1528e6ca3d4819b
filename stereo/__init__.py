"""stereo: the EMCStereo network, its datasets, training, evaluation and inference backends.

The network and checkpoint names are imported on first use, so that tools which only need
`stereo.io`, `stereo.synth` or the command-line plumbing do not pay for importing torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "EMCStereo": "stereo.model",
    "ModelConfig": "stereo.model",
    "CheckpointError": "stereo.checkpoints",
    "load_model": "stereo.checkpoints",
    "save_checkpoint": "stereo.checkpoints",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'stereo' has no attribute {name!r}")
