"""Light for the randomized scenes: the regime of the day, its sky with clouds and the sun's glow.

Regimes (`LIGHT_REGIMES`), drawn per scene:
- 'sun': a clear or broken sky, sun 20–65° up from any side;
- 'backlight': the sun 8–35° up within 35° of the view direction, a bright hazy sky: the tree faces
  the camera with its unlit side, dark against the sky (silhouettes), and auto-exposure metered on
  the whole frame keeps it dark;
- 'low_sun': the sun 2–15° up, warm light, strong side lighting;
- 'overcast': a grey sky, no sun, flat bright ambient light;
- 'dusk': the sun below the horizon, a dim blue ambient light under an orange-to-blue sky (the
  camera's gain and noise go up).
The light model is the renderer's (`primitives.Lighting`: Lambert sun, ambient, haze); cast shadows
are not drawn.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stereo.synth.primitives import Lighting, dot3, norm3, unit
from stereo.synth.sky import Sky
from stereo.synth.textures import cloud_tile

LIGHT_REGIMES = ("sun", "backlight", "low_sun", "overcast", "dusk")
#: the regime of scenes that do not randomize light
DEFAULT_REGIME = "sun"


@dataclass(frozen=True)
class SunSky(Sky):
    """A `Sky` with the sun's glow around `sun_direction` (unit, camera frame), `glow_rgb` at its peak, seen
    through a veil of `veil_opacity` (0: none) and colour `veil_rgb`: hail netting overhead, whose mesh is far
    finer than a pixel, so what reaches the camera is the sky dimmed and tinted by the threads."""

    sun_direction: np.ndarray
    glow_rgb: np.ndarray
    glow_width_rad: float
    veil_rgb: np.ndarray = field(default_factory=lambda: np.zeros(3))
    veil_opacity: float = 0.0

    def colour(self, directions: np.ndarray) -> np.ndarray:
        """RGB `(N, 3)` seen along camera-frame `directions` `(N, 3)` (any length)."""
        base = super().colour(directions)
        cosine = dot3(directions.astype(np.float64), self.sun_direction) / norm3(directions.astype(np.float64))
        angle = np.arccos(np.clip(cosine, -1.0, 1.0))
        glow = np.exp(-((angle / self.glow_width_rad) ** 2)) + 0.25 * np.exp(-angle / (4 * self.glow_width_rad))
        seen = (base + glow[:, None] * self.glow_rgb[None, :]) * (1.0 - self.veil_opacity)
        return np.asarray(seen + self.veil_opacity * self.veil_rgb[None, :], dtype=np.float32)


@dataclass(frozen=True)
class DrawnLight:
    """A scene's light: `regime`, its `sky` and `lighting`, and the mean luma auto-exposure aims at."""

    regime: str
    sky: SunSky
    lighting: Lighting
    exposure_target: float


def _sun_world(elevation_deg: float, azimuth_rad: float) -> np.ndarray:
    """Unit vector toward the sun in the world frame (y down); azimuth 0 is world +z."""
    elevation = np.radians(elevation_deg)
    return np.array(
        [np.cos(elevation) * np.sin(azimuth_rad), -np.sin(elevation), np.cos(elevation) * np.cos(azimuth_rad)]
    )


def draw_light(
    rng: np.random.Generator, regime: str, world_from_camera: np.ndarray, view_azimuth_rad: float
) -> DrawnLight:
    """The sky and light of `regime` for a camera whose axes in the world (y down) are the columns of
    `world_from_camera` (3×3) and which looks along world azimuth `view_azimuth_rad` (0: +z)."""
    if regime not in LIGHT_REGIMES:
        raise ValueError(f"unknown light regime {regime!r}; known: {', '.join(LIGHT_REGIMES)}")
    jitter = rng.uniform(0.85, 1.15)
    azimuth = rng.uniform(0.0, 2 * np.pi)
    if regime == "sun":
        elevation, cover = rng.uniform(20.0, 65.0), rng.uniform(0.0, 0.5)
        zenith, horizon, clouds = np.array([0.25, 0.45, 0.85]), np.array([0.75, 0.83, 0.93]), np.array([0.96] * 3)
        sun, ambient, glow, target = np.array([1.0, 0.95, 0.85]), np.array([0.33, 0.38, 0.48]), 0.6, (0.36, 0.5)
    elif regime == "backlight":
        elevation, cover = rng.uniform(8.0, 35.0), rng.uniform(0.0, 0.4)
        azimuth = view_azimuth_rad + np.radians(rng.uniform(-35.0, 35.0))
        zenith, horizon, clouds = np.array([0.55, 0.68, 0.9]), np.array([0.95, 0.95, 0.93]), np.array([1.0] * 3)
        sun, ambient, glow, target = np.array([1.0, 0.93, 0.8]), np.array([0.12, 0.13, 0.16]), 2.5, (0.4, 0.55)
    elif regime == "low_sun":
        elevation, cover = rng.uniform(2.0, 15.0), rng.uniform(0.0, 0.5)
        zenith, horizon, clouds = np.array([0.3, 0.45, 0.75]), np.array([0.95, 0.75, 0.55]), np.array([1.0, 0.8, 0.65])
        sun, ambient, glow, target = np.array([1.1, 0.75, 0.45]), np.array([0.22, 0.25, 0.35]), 1.5, (0.32, 0.45)
    elif regime == "overcast":
        elevation, cover = rng.uniform(20.0, 60.0), rng.uniform(0.5, 0.9)
        zenith, horizon, clouds = np.array([0.7, 0.72, 0.76]), np.array([0.85, 0.86, 0.88]), np.array([0.6, 0.61, 0.64])
        sun, ambient, glow, target = np.array([0.15, 0.15, 0.14]), np.array([0.75, 0.77, 0.8]), 0.0, (0.36, 0.5)
    else:  # dusk
        elevation, cover = rng.uniform(-8.0, -1.0), rng.uniform(0.0, 0.6)
        zenith, horizon, clouds = np.array([0.06, 0.08, 0.2]), np.array([0.55, 0.32, 0.18]), np.array([0.3, 0.2, 0.2])
        sun, ambient, glow, target = np.zeros(3), np.array([0.05, 0.06, 0.1]), 0.3, (0.2, 0.32)
    sun_camera = unit(_sun_world(elevation, azimuth) @ world_from_camera)
    sky = SunSky(
        world_from_camera,
        zenith * jitter,
        horizon,
        clouds,
        cloud_tile(rng, cover),
        rng.uniform(0.05, 0.2),
        sun_camera,
        np.array([1.0, 0.9, 0.75]) * glow,
        np.radians(rng.uniform(2.0, 6.0)),
    )
    lighting = Lighting(sun_camera, sun * jitter, ambient * rng.uniform(0.8, 1.2), horizon, rng.uniform(60.0, 250.0))
    return DrawnLight(regime, sky, lighting, float(rng.uniform(*target)))
