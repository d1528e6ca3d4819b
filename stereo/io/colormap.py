"""Disparity maps as colour images for people: overlays, debug output, the demo."""

from __future__ import annotations

import cv2
import numpy as np


def colorize_disparity(disp: np.ndarray, max_disp: float | None = None) -> np.ndarray:
    """Colour a float `H×W` disparity (pixels) as RGB `uint8` `H×W×3` with the turbo map; invalid pixels black.

    Near (large disparity) is red, far is blue. `max_disp` fixes the top of the scale (compare maps
    across frames); by default it is the largest valid disparity. Invalid: non-finite or ≤ 0.
    """
    disp = np.asarray(disp, dtype=np.float32)
    if disp.ndim != 2:
        raise ValueError(f"colorize_disparity expects an H×W disparity map, got shape {disp.shape}")
    if max_disp is not None and not max_disp > 0:
        raise ValueError(f"max_disp must be positive, got {max_disp}")
    valid = np.isfinite(disp) & (disp > 0)
    top = float(max_disp) if max_disp is not None else (float(disp[valid].max()) if valid.any() else 1.0)
    levels = np.zeros(disp.shape, dtype=np.uint8)
    levels[valid] = np.rint(np.clip(disp[valid] / top, 0.0, 1.0) * 255.0).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(levels, cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    rgb[~valid] = 0
    return rgb
