"""Surface-anchored procedural textures: periodic tiles sampled at a hit point's surface coordinates.

Every tile is periodic (built by filtering white noise in the Fourier domain), so surfaces can
wrap it without seams. A colour is looked up from the hit point's coordinates *on the surface*
(along / around a branch axis, metres on a plane, direction of a sky ray), never from the pixel,
so the left and right views see the same texture on the same surface point. Tiles are float32
`S×S×C` with values in [0, 1]; rows index the second surface coordinate, columns the first.
"""

from __future__ import annotations

import cv2
import numpy as np

TILE_SIZE = 256
_REMAP_WIDTH = 1024
#: Pre-blurred copies per tile: level l is blurred with σ = 2^(l−1) texels (level 0 sharp).
MIP_LEVELS = 6

#: Bark albedos (RGB in [0, 1]) with how deep their furrows are and whether they carry lenticels.
BARK_KINDS: dict[str, tuple[tuple[float, float, float], float, bool]] = {
    "grey_brown": ((0.42, 0.36, 0.30), 0.55, False),
    "dark_brown": ((0.30, 0.22, 0.16), 0.60, False),
    "smooth_grey": ((0.52, 0.51, 0.48), 0.20, False),
    "reddish": ((0.45, 0.28, 0.20), 0.35, True),
    "olive": ((0.38, 0.37, 0.27), 0.45, False),
    "birch": ((0.80, 0.78, 0.72), 0.10, True),
}


def periodic_noise(
    rng: np.random.Generator, cycles_u: float, cycles_v: float, size: int = TILE_SIZE, slope: float = 2.0
) -> np.ndarray:
    """Seamless noise `size×size` (float32, zero mean, unit std) with features of about 1/cycles of the tile.

    `cycles_u` sets the feature scale along columns, `cycles_v` along rows (anisotropic when they
    differ); `slope` is the spectral fall-off beyond that scale (larger = smoother).
    """
    white = rng.standard_normal((size, size))
    fv = np.fft.fftfreq(size)[:, None] * size
    fu = np.fft.rfftfreq(size)[None, :] * size
    gain = (1.0 + (fu / cycles_u) ** 2 + (fv / cycles_v) ** 2) ** (-slope / 2.0)
    gain[0, 0] = 0.0
    field = np.fft.irfft2(np.fft.rfft2(white) * gain, s=(size, size))
    return ((field - field.mean()) / (field.std() + 1e-12)).astype(np.float32)


def unit_range(noise: np.ndarray) -> np.ndarray:
    """Map zero-mean unit-std noise to [0, 1] smoothly."""
    return (0.5 + 0.5 * np.tanh(0.8 * noise)).astype(np.float32)


def bark_tile(rng: np.random.Generator, kind: str) -> np.ndarray:
    """RGB bark `S×S×3`: columns run along the branch axis, rows around it (furrows run along the axis)."""
    base, furrow_depth, lenticels = BARK_KINDS[kind]
    base_rgb = np.clip(np.array(base) * rng.uniform(0.85, 1.15) + rng.normal(0, 0.03, 3), 0.05, 0.95)
    furrows = np.exp(-((periodic_noise(rng, 2.5, 22.0, slope=2.5) / 0.45) ** 2))
    grain = unit_range(periodic_noise(rng, 48.0, 48.0, slope=1.5))
    patches = unit_range(periodic_noise(rng, 2.0, 2.0))
    shade = (0.72 + 0.42 * grain) * (1.0 - furrow_depth * furrows)
    colour = base_rgb[None, None, :] * shade[..., None] * (0.8 + 0.4 * patches[..., None])
    lichen = np.clip(patches - 0.62, 0.0, 1.0)[..., None] * rng.uniform(0.0, 2.0)
    colour = colour * (1 - lichen) + np.array([0.45, 0.52, 0.36]) * lichen
    if lenticels:
        marks = periodic_noise(rng, 40.0, 5.0, slope=3.0) > 1.8
        colour[marks] *= 0.35
    return np.clip(colour, 0.0, 1.0).astype(np.float32)


def foliage_tile(rng: np.random.Generator, hue: tuple[float, float, float], coverage: float) -> np.ndarray:
    """RGBA far foliage `S×S×4`: leaf clumps whose alpha (0/1) covers `coverage` of the tile."""
    clumps = periodic_noise(rng, 5.0, 5.0)
    leaves = periodic_noise(rng, 36.0, 36.0, slope=1.5)
    density = clumps + 0.3 * leaves
    threshold = np.quantile(density, 1.0 - coverage)
    light = unit_range(0.9 * leaves + 0.7 * clumps)
    colour = np.array(hue)[None, None, :] * (0.45 + 0.9 * light[..., None])
    alpha = (density > threshold).astype(np.float32)
    return np.concatenate([np.clip(colour, 0, 1), alpha[..., None]], axis=2).astype(np.float32)


def ground_tile(
    rng: np.random.Generator, grass: tuple[float, float, float], soil: tuple[float, float, float]
) -> np.ndarray:
    """RGB ground `S×S×3`: grass and soil patches with fine blades/litter."""
    patches = unit_range(periodic_noise(rng, 3.0, 3.0))
    fine = unit_range(periodic_noise(rng, 60.0, 60.0, slope=1.2))
    mix = np.clip((patches - 0.45) * 1.8 + 0.5, 0.0, 1.0)[..., None]
    colour = (np.array(grass) * mix + np.array(soil) * (1 - mix)) * (0.55 + 0.9 * fine[..., None])
    return np.clip(colour, 0.0, 1.0).astype(np.float32)


def cloud_tile(rng: np.random.Generator, cover: float) -> np.ndarray:
    """Cloud opacity `S×S×1` in [0, 1] covering about `cover` of the sky."""
    field = periodic_noise(rng, 4.0, 3.0, slope=2.2)
    threshold = np.quantile(field, 1.0 - cover)
    return np.clip((field - threshold) * 1.5, 0.0, 1.0)[..., None].astype(np.float32)


def detail_tile(rng: np.random.Generator) -> np.ndarray:
    """Fine grey detail `S×S×1` around 1.0 (leaf blades' veins and mottling)."""
    return (0.8 + 0.4 * unit_range(periodic_noise(rng, 24.0, 6.0, slope=1.6)))[..., None].astype(np.float32)


def sample_tile(tile: np.ndarray, u_px: np.ndarray, v_px: np.ndarray) -> np.ndarray:
    """Bilinear, wrapping lookup of `tile` (`S×S×C`) at tile coordinates (columns `u_px`, rows `v_px`).

    `u_px`, `v_px` `(N,)` each → `(N, C)`.
    """
    tile = np.ascontiguousarray(tile)
    size_v, size_u = tile.shape[:2]
    n = u_px.size
    if n == 0:
        return np.zeros((0, tile.shape[2]), dtype=tile.dtype)
    padded = -(-n // _REMAP_WIDTH) * _REMAP_WIDTH
    map_u = np.zeros(padded, dtype=np.float32)
    map_v = np.zeros(padded, dtype=np.float32)
    map_u[:n] = np.mod(u_px, size_u)
    map_v[:n] = np.mod(v_px, size_v)
    shape = (padded // _REMAP_WIDTH, _REMAP_WIDTH)
    out = cv2.remap(tile, map_u.reshape(shape), map_v.reshape(shape), cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.reshape(padded, -1)[:n]


def periodic_blur(tile: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur (σ in texels) of a periodic tile `S×S×C`, wrapping around its edges."""
    pad = min(int(np.ceil(3 * sigma)), tile.shape[0])
    padded = np.pad(tile, ((pad, pad), (pad, pad), (0, 0)), mode="wrap")
    blurred = cv2.GaussianBlur(padded, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    if blurred.ndim == 2:
        blurred = blurred[..., None]
    return np.ascontiguousarray(blurred[pad : pad + tile.shape[0], pad : pad + tile.shape[1]], dtype=np.float32)


class MipTile:
    """A periodic tile with blurred copies, so far or oblique surfaces are filtered instead of aliased.

    The level is chosen from the footprint of one image sample on the surface, measured in
    texels; both views use the left camera's footprint so they pick the same level.
    """

    def __init__(self, tile: np.ndarray) -> None:
        tile = np.ascontiguousarray(tile, dtype=np.float32)
        self.levels = [tile] + [periodic_blur(tile, 2.0 ** (level - 1)) for level in range(1, MIP_LEVELS)]

    @property
    def channels(self) -> int:
        """Channels per texel."""
        return self.levels[0].shape[2]

    def sample(self, u_px: np.ndarray, v_px: np.ndarray, footprint_texels: np.ndarray) -> np.ndarray:
        """`sample_tile` at the level matching each sample's footprint (texels per image sample) → `(N, C)`."""
        level = np.clip(np.rint(np.log2(np.maximum(footprint_texels, 1.0))), 0, MIP_LEVELS - 1).astype(np.int64)
        out = np.empty((u_px.size, self.channels), dtype=np.float32)
        for index, count in enumerate(np.bincount(level, minlength=MIP_LEVELS)):
            if count:
                sel = np.flatnonzero(level == index)
                out[sel] = sample_tile(self.levels[index], u_px[sel], v_px[sel])
        return out
