"""Leaf blades: flat pointed ellipses on the twigs, ray-cast exactly in batches.

A blade lies in the plane through `centre` with unit `normal`; in-plane coordinates along
`e1` (−1..1 over the half-length) and across (−1..1 over the half-width) must satisfy
`|across| ≤ (1 − along²)^0.75`, a leaf outline with pointed ends.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from stereo.synth.camera import RayGrid
from stereo.synth.primitives import NEAR_M, Hits, Lighting, box_chunks, cross3, nearest_per_sample, rowdot
from stereo.synth.textures import TILE_SIZE, MipTile

_SQUARE = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])


@dataclass(frozen=True)
class Leaf:
    """A flat leaf blade: centre, unit normal, unit length axis `e1` (⊥ normal), half-length and half-width (m)."""

    centre: np.ndarray
    normal: np.ndarray
    e1: np.ndarray
    half_length: float
    half_width: float
    colour: np.ndarray
    instance_id: int


class LeafBatch:
    """All leaves of a scene, sharing one detail tile (veins, mottling)."""

    def __init__(self, leaves: Sequence[Leaf], detail: MipTile) -> None:
        self.detail = detail
        self.centre = np.array([leaf.centre for leaf in leaves], dtype=np.float64).reshape(-1, 3)
        self.normal = np.array([leaf.normal for leaf in leaves], dtype=np.float64).reshape(-1, 3)
        self.e1 = np.array([leaf.e1 for leaf in leaves], dtype=np.float64).reshape(-1, 3)
        self.e2 = cross3(self.normal, self.e1)
        self.half_length = np.array([leaf.half_length for leaf in leaves])
        self.half_width = np.array([leaf.half_width for leaf in leaves])
        self.colour = np.array([leaf.colour for leaf in leaves], dtype=np.float64).reshape(-1, 3)
        self.ids = np.array([leaf.instance_id for leaf in leaves], dtype=np.uint16)
        self.hulls = (
            self.centre[:, None, :]
            + _SQUARE[None, :, 0, None] * (self.half_length[:, None] * self.e1)[:, None, :]
            + _SQUARE[None, :, 1, None] * (self.half_width[:, None] * self.e2)[:, None, :]
        )
        order = np.argsort(self.centre[:, 2], kind="stable")
        for name in ("centre", "normal", "e1", "e2", "half_length", "half_width", "colour", "ids", "hulls"):
            setattr(self, name, getattr(self, name)[order])

    def instance_ids(self, part: np.ndarray) -> np.ndarray:
        """Batch protocol: mask ids (uint16 `(N,)`) of the given parts."""
        return self.ids[part]

    def _blade(self, rel: np.ndarray, part: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Blade coordinates (along, across; −1..1) of in-plane offsets `rel` `(N, 3)` from the centres."""
        return rowdot(rel, self.e1[part]) / self.half_length[part], rowdot(rel, self.e2[part]) / self.half_width[part]

    def hits(self, rays: RayGrid, depth: np.ndarray) -> Iterator[Hits]:
        """Batch protocol: nearest hits nearer than `depth` (`Hs×Ws`, m), chunk by chunk."""
        if self.ids.size == 0:
            return
        to_centre = self.centre - rays.origin[None, :]
        reach = rowdot(to_centre, self.normal)
        width = rays.shape[1]
        for part, rows, cols in box_chunks(rays, self.hulls):
            dx, dy = rays.dx[cols], rays.dy[rows]
            n = self.normal[part]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = reach[part] / (n[:, 0] * dx + n[:, 1] * dy + n[:, 2])
            index = rows * width + cols
            sel = np.flatnonzero((t > NEAR_M) & (t < depth.ravel()[index]))
            if sel.size == 0:
                continue
            part, index, t = part[sel], index[sel], t[sel]
            rel = t[:, None] * np.stack([dx[sel], dy[sel], np.ones(sel.size)], axis=1) - to_centre[part]
            along, across = self._blade(rel, part)
            inside = np.flatnonzero(np.abs(across) <= np.clip(1.0 - along * along, 0.0, None) ** 0.75)
            if inside.size:
                yield nearest_per_sample(index[inside], t[inside], part[inside])

    def shade(self, points: np.ndarray, part: np.ndarray, light: Lighting, sample_angle: float) -> np.ndarray:
        """Batch protocol: RGB `(N, 3)` of hit `points` `(N, 3)` on the given parts under `light`."""
        along, across = self._blade(points - self.centre[part], part)
        normals = self.normal[part]
        footprint = light.footprint_m(points, normals, sample_angle) / (2 * self.half_length[part] / TILE_SIZE)
        vein = 1.0 + 0.18 * np.exp(-((across / 0.07) ** 2))
        detail = self.detail.sample(
            (along + 1) * 0.5 * TILE_SIZE + 61.0 * part, (across + 1) * 0.5 * TILE_SIZE, footprint
        )[:, 0]
        albedo = self.colour[part] * (vein * detail)[:, None]
        return albedo * light.diffuse(normals, two_sided=True)
