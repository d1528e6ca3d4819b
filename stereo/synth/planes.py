"""Background planes: the ground, far rows of foliage and a leaf canopy overhead.

A plane layer is cast over the whole image at once (every ray may reach it). Its texture is
anchored to metric plane coordinates (u along `eu`, v along `ev`), holes in foliage come from
the tile's alpha, and a tree row's canopy line is a periodic height profile over u.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from stereo.synth.camera import RayGrid
from stereo.synth.primitives import FAR_M, NEAR_M, Hits, Lighting, cross3, dot3, unit
from stereo.synth.textures import TILE_SIZE, MipTile, sample_tile


@dataclass(frozen=True)
class PlaneLayer:
    """A textured plane through `point` with unit axes `eu`, `ev` (metres; `ev` points up for walls).

    `tile` (RGB) repeats every `tile_m` metres; `alpha` (optional, `S×S×1` on the same grid)
    marks holes where it is below 0.5. `profile`
    (optional, m) limits the layer to `v < profile(u)`: the canopy line of a tree row, sampled
    periodically every `profile_period_m`, and `floor` (optional, m) to `v ≥ floor` (the
    bottom of the crowns). `light_factor` scales the sun on it (foliage is not a
    flat Lambertian surface). Its pixels are background (mask id 0).
    """

    point: np.ndarray
    eu: np.ndarray
    ev: np.ndarray
    tile: MipTile
    tile_m: float
    light_factor: float
    alpha: np.ndarray | None = None
    profile: np.ndarray | None = None
    profile_period_m: float = 1.0
    floor: float | None = None

    @property
    def normal(self) -> np.ndarray:
        """Unit normal `eu × ev`."""
        return unit(cross3(self.eu, self.ev))

    def instance_ids(self, part: np.ndarray) -> np.ndarray:
        """Batch protocol: mask ids (uint16 `(N,)`) of the given parts."""
        return np.zeros(part.size, dtype=np.uint16)

    def _along(self, axis: np.ndarray, rays: RayGrid, t: np.ndarray) -> np.ndarray:
        """Plane coordinate (m, float32 `Hs×Ws`) along unit `axis` of the points at depth `t` on every ray."""
        a = axis.astype(np.float32)
        slope = a[0] * rays.dx.astype(np.float32)[None, :] + (a[1] * rays.dy.astype(np.float32) + a[2])[:, None]
        return np.float32((rays.origin - self.point) @ axis) + t * slope

    def hits(self, rays: RayGrid, depth: np.ndarray) -> Iterator[Hits]:
        """Batch protocol: nearest hits nearer than `depth` (`Hs×Ws`, m), chunk by chunk."""
        n = self.normal.astype(np.float32)
        denom = n[0] * rays.dx.astype(np.float32)[None, :] + (n[1] * rays.dy.astype(np.float32) + n[2])[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.float32((self.point - rays.origin) @ self.normal) / denom
        index = np.flatnonzero((t > NEAR_M) & (t < depth) & (t < FAR_M))
        if index.size and (self.profile is not None or self.alpha is not None):
            u = self._along(self.eu, rays, t).ravel()[index]
            v = self._along(self.ev, rays, t).ravel()[index]
            index = index[self._opaque(u, v)]
        if index.size:
            yield Hits(index, t.ravel()[index].astype(np.float64), np.zeros(index.size, dtype=np.int64))

    def _opaque(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Which plane points (u, v in m) are foliage rather than a hole or sky above the canopy line."""
        keep = np.ones(u.size, dtype=bool) if self.floor is None else v >= np.float32(self.floor)
        if self.profile is not None:
            table = np.append(self.profile, self.profile[0]).astype(np.float32)
            position = np.mod(u * np.float32(self.profile.size / self.profile_period_m), self.profile.size)
            cell = np.minimum(position.astype(np.int64), self.profile.size - 1)
            frac = position - cell
            keep &= v < table[cell] * (1 - frac) + table[cell + 1] * frac
        if self.alpha is not None:
            scale = np.float32(TILE_SIZE / self.tile_m)
            keep &= sample_tile(self.alpha, u * scale, v * scale)[:, 0] >= 0.5
        return keep

    def shade(self, points: np.ndarray, part: np.ndarray, light: Lighting, sample_angle: float) -> np.ndarray:
        """Batch protocol: RGB `(N, 3)` of hit `points` `(N, 3)` on the given parts under `light`."""
        rel = points - self.point
        u, v = dot3(rel, self.eu), dot3(rel, self.ev)
        normals = np.broadcast_to(self.normal, points.shape)
        footprint = light.footprint_m(points, normals, sample_angle) / (self.tile_m / TILE_SIZE)
        albedo = self.tile.sample(u / self.tile_m * TILE_SIZE, v / self.tile_m * TILE_SIZE, footprint)
        return albedo * (light.ambient_rgb + self.light_factor * light.sun_rgb)[None, :]
