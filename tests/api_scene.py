"""A small exact stereo scene for the API tests: a textured bar (the branch) before a textured wall."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

FOCAL_PX = 400.0
BASELINE_M = 0.1
BAR_DISPARITY = 32
WALL_DISPARITY = 8
BAR_DEPTH_M = FOCAL_PX * BASELINE_M / BAR_DISPARITY  # 1.25 m


@dataclass
class Scene:
    left: np.ndarray  # uint8 H×W×3 RGB
    right: np.ndarray
    mask: np.ndarray  # uint8 H×W, 255 on the bar in the left image

    def png(self, which: str) -> bytes:
        image = getattr(self, which)
        ok, data = cv2.imencode(".png", image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        assert ok
        return data.tobytes()


def bar_scene(width: int = 320, height: int = 256, seed: int = 0) -> Scene:
    """Left/right views of a fronto-parallel bar at BAR_DEPTH_M over a wall at 5 m; exact by construction."""
    rng = np.random.default_rng(seed)
    wall = cv2.GaussianBlur(rng.integers(0, 256, (height, width + 64, 3), dtype=np.uint8), (3, 3), 0)
    bar_tex = cv2.GaussianBlur(rng.integers(0, 256, (height, width + 64, 3), dtype=np.uint8), (3, 3), 0)
    rows, cols = np.mgrid[0:height, 0:width]
    on_bar = (np.abs(rows - 128) <= 10) & (cols >= 80) & (cols < 280)
    left = np.where(on_bar[..., None], bar_tex[rows, cols], wall[rows, cols])
    # a right-image pixel at x shows the left-image point x + d of whichever surface is in front
    bar_in_right = (np.abs(rows - 128) <= 10) & (cols + BAR_DISPARITY >= 80) & (cols + BAR_DISPARITY < 280)
    right = np.where(bar_in_right[..., None], bar_tex[rows, cols + BAR_DISPARITY], wall[rows, cols + WALL_DISPARITY])
    return Scene(left.astype(np.uint8), right.astype(np.uint8), (on_bar * 255).astype(np.uint8))
