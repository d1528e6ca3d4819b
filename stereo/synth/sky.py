"""The sky: what rays that hit nothing see, infinitely far away (depth inf, disparity 0).

Its colour depends only on the ray direction, which is the same for both cameras at infinity,
so the views agree there too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereo.synth.primitives import dot3, norm3
from stereo.synth.textures import TILE_SIZE, sample_tile


@dataclass(frozen=True)
class Sky:
    """Colour of rays that hit nothing (infinitely far): a zenith/horizon gradient with clouds.

    `world_from_camera` (3×3) turns camera-frame directions into a world frame with y down.
    """

    world_from_camera: np.ndarray
    zenith_rgb: np.ndarray
    horizon_rgb: np.ndarray
    cloud_rgb: np.ndarray
    clouds: np.ndarray
    cloud_scale: float

    def colour(self, directions: np.ndarray) -> np.ndarray:
        """RGB `(N, 3)` seen along camera-frame `directions` `(N, 3)` (any length)."""
        d = directions.astype(np.float32)
        inv_len = 1.0 / norm3(d)
        wx, wy, wz = (dot3(d, row) * inv_len for row in self.world_from_camera.astype(np.float32))
        up = np.clip(-wy, 0.0, 1.0)
        gradient = np.sqrt(up)[:, None]
        colour = self.horizon_rgb * (1 - gradient) + self.zenith_rgb * gradient
        scale = self.cloud_scale * TILE_SIZE / np.maximum(up, 0.05)
        cover = sample_tile(self.clouds, wx * scale, wz * scale)[:, 0]
        cover *= np.clip((up - 0.03) / 0.2, 0.0, 1.0)
        return colour + (self.cloud_rgb[None, :] - colour) * cover[:, None]
