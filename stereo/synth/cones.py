"""Tapered cylinders (trunks, branches, twigs), ray-cast exactly in batches.

A cone's surface is the set of points at distance `r0 + k·s` from its axis, `0 ≤ s ≤ length`
(s: metres along the axis from the base, k = dr/ds); its tip end is closed by a flat disc. A
ray `o + t·d` meets it where `|w|² − (w·a)² = (r0 + k·(w·a))²` with `w = o + t·d − base`: a
quadratic in t, solved per sample. Long cones are cut into pieces along the axis (the same
surface) so each piece's image box stays tight.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from stereo.synth.camera import RayGrid, SynthCamera
from stereo.synth.primitives import (
    NEAR_M,
    Hits,
    Lighting,
    box_chunks,
    nearest_per_sample,
    norm3,
    perpendicular_frames,
    rowdot,
)
from stereo.synth.textures import TILE_SIZE, MipTile

#: Cone parts closer than this (m, plus their radius) to the cameras' plane are not cast.
CLIP_Z_M = 0.05
_SQUARE = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])


def _rounded(vector: np.ndarray) -> list[float]:
    """A 3-vector as plain floats rounded to the µm, for error messages."""
    return [round(float(v), 6) for v in vector]


@dataclass(frozen=True)
class BarkMaterial:
    """A bark tile and how it wraps a cylinder: `around` tiles per turn, `along_m` metres per tile."""

    tile: MipTile
    around: int
    along_m: float
    tint: np.ndarray = field(default_factory=lambda: np.ones(3))


@dataclass(frozen=True)
class Cone:
    """A tapered cylinder: axis from `base` along unit `axis` for `length` m, radius `r0` → `r1` (m)."""

    base: np.ndarray
    axis: np.ndarray
    length: float
    r0: float
    r1: float
    material: BarkMaterial
    instance_id: int

    def front_range(self) -> tuple[float, float]:
        """Axis range (m) whose surface lies at least `CLIP_Z_M` in front of the cameras' plane.

        What lies behind is cut off: trunks reaching over or behind the camera would otherwise
        give boxes over the whole image. Scenes keep everything in view ≥ 0.2 m away, so the
        cut never removes a visible surface.
        """
        z_min = CLIP_Z_M + max(self.r0, self.r1)
        z0, dz = float(self.base[2]), float(self.axis[2])
        if abs(dz) < 1e-12:
            return (0.0, self.length) if z0 >= z_min else (0.0, 0.0)
        s_cross = (z_min - z0) / dz
        lo, hi = (max(0.0, s_cross), self.length) if dz > 0 else (0.0, min(self.length, s_cross))
        return (lo, hi) if hi > lo else (0.0, 0.0)

    def pieces_for(self, camera: SynthCamera, s_range: tuple[float, float]) -> int:
        """How many pieces of the axis range keep each piece's image box from being mostly empty (0–64)."""
        length = s_range[1] - s_range[0]
        if length <= 0:
            return 0
        z_near = max(min(self.base[2] + s * self.axis[2] for s in s_range), CLIP_Z_M)
        length_px = camera.focal_px * length / z_near
        width_px = 2.0 * max(self.r0, self.r1) * camera.focal_px / z_near
        return int(np.clip(np.ceil(length_px / max(3.0 * width_px, 12.0)), 1, 64))

    def radius_at(self, s: float) -> float:
        """Radius (m) of the surface `s` m along the axis from the base."""
        return self.r0 + (self.r1 - self.r0) * s / self.length

    def exit_distance(self, origin: np.ndarray, direction: np.ndarray) -> float:
        """Distance (m) along unit `direction` `(3,)` from `origin` `(3,)`, a point inside the cone, to
        where that ray leaves its side surface (exact: the positive root of the module's quadratic).

        Where a branch axis starting inside a trunk leaves the bark. Raises `ValueError` when
        `origin` is not inside, or the ray leaves through an end disc or never leaves.
        """
        k = (self.r1 - self.r0) / self.length
        w = np.asarray(origin, dtype=np.float64) - self.base
        d = np.asarray(direction, dtype=np.float64)
        wa, da = float(w @ self.axis), float(d @ self.axis)
        w_perp, d_perp = w - wa * self.axis, d - da * self.axis
        radius0 = self.r0 + k * wa
        quad_a = float(d_perp @ d_perp) - k * k * da * da
        quad_b = 2.0 * (float(w_perp @ d_perp) - k * da * radius0)
        quad_c = float(w_perp @ w_perp) - radius0 * radius0
        if not (0.0 <= wa <= self.length and radius0 > 0.0 and quad_c < 0.0):
            raise ValueError(f"exit_distance: origin {_rounded(origin)} is not inside the cone")
        disc = quad_b * quad_b - 4.0 * quad_a * quad_c
        # the two roots in the cancellation-free form q/A, C/q; the exit is the nearest one ahead
        q = -0.5 * (quad_b + np.copysign(np.sqrt(max(disc, 0.0)), quad_b))
        roots = [
            r
            for r in ((q / quad_a if quad_a != 0.0 else np.inf), (quad_c / q if q != 0.0 else np.inf))
            if 0.0 < r < np.inf and radius0 + k * da * r >= 0.0
        ]
        if disc < 0.0 or not roots:
            raise ValueError(f"exit_distance: the ray along {_rounded(direction)} never leaves the side surface")
        t = min(roots)
        if not 0.0 <= wa + t * da <= self.length:
            raise ValueError(
                f"exit_distance: the ray along {_rounded(direction)} leaves through an end, not the side surface"
            )
        return float(t)


class ConeBatch:
    """Many cone pieces cast together; part k is piece k (its cone's geometry, range, material, id)."""

    def __init__(self, cones: Sequence[Cone], camera: SynthCamera) -> None:
        ranges = np.array([cone.front_range() for cone in cones], dtype=np.float64).reshape(-1, 2)
        counts = np.array([cone.pieces_for(camera, tuple(r)) for cone, r in zip(cones, ranges)], dtype=np.int64)
        owner = np.repeat(np.arange(len(cones)), counts)
        first = np.repeat(np.cumsum(counts) - counts, counts)
        fraction = (np.arange(owner.size) - first) / np.maximum(counts[owner], 1)
        length = np.array([c.length for c in cones])[owner]
        start, span = ranges[owner, 0], ranges[owner, 1] - ranges[owner, 0]
        self.base = np.array([c.base for c in cones], dtype=np.float64)[owner]
        self.axis = np.array([c.axis for c in cones], dtype=np.float64)[owner]
        self.length = length
        self.r0 = np.array([c.r0 for c in cones])[owner]
        self.r1 = np.array([c.r1 for c in cones])[owner]
        self.slope = (self.r1 - self.r0) / self.length
        self.s_lo = start + fraction * span
        self.s_hi = start + (fraction + 1.0 / np.maximum(counts[owner], 1)) * span
        self.capped = np.isclose(self.s_hi, length)
        self.ids = np.array([c.instance_id for c in cones], dtype=np.uint16)[owner]
        tiles = {id(c.material.tile): c.material.tile for c in cones}
        tile_keys = list(tiles)
        self.tiles = [tiles[key] for key in tile_keys]
        self.tile_index = np.array([tile_keys.index(id(c.material.tile)) for c in cones], dtype=np.int64)[owner]
        self.around = np.array([c.material.around for c in cones], dtype=np.float64)[owner]
        self.along_m = np.array([c.material.along_m for c in cones])[owner]
        self.tint = np.array([c.material.tint for c in cones], dtype=np.float64).reshape(-1, 3)[owner]
        self.e1, self.e2 = perpendicular_frames(self.axis) if owner.size else (self.axis, self.axis)
        ends = [self.base + s[:, None] * self.axis for s in (self.s_lo, self.s_hi)]
        radii = [self.r0 + self.slope * s for s in (self.s_lo, self.s_hi)]
        # a frustum is the convex hull of its end discs; each disc lies in the square ±r·e1 ± r·e2
        square = _SQUARE[None, :, 0, None] * self.e1[:, None, :] + _SQUARE[None, :, 1, None] * self.e2[:, None, :]
        self.hulls = np.concatenate([e[:, None, :] + r[:, None, None] * square for e, r in zip(ends, radii)], axis=1)
        order = np.argsort(self.hulls[:, :, 2].min(axis=1), kind="stable")
        for name in (
            "base",
            "axis",
            "length",
            "r0",
            "r1",
            "slope",
            "s_lo",
            "s_hi",
            "capped",
            "ids",
            "tile_index",
            "around",
            "along_m",
            "tint",
            "e1",
            "e2",
            "hulls",
        ):
            setattr(self, name, getattr(self, name)[order])

    def instance_ids(self, part: np.ndarray) -> np.ndarray:
        """Batch protocol: mask ids (uint16 `(N,)`) of the given parts."""
        return self.ids[part]

    def hits(self, rays: RayGrid, depth: np.ndarray) -> Iterator[Hits]:
        """Batch protocol: nearest hits nearer than `depth` (`Hs×Ws`, m), chunk by chunk."""
        if self.ids.size == 0:
            return
        w0 = rays.origin[None, :] - self.base
        s0 = rowdot(w0, self.axis)
        radius0 = self.r0 + self.slope * s0
        c = rowdot(w0, w0) - s0 * s0 - radius0 * radius0
        beta = s0 + self.slope * radius0
        width = rays.shape[1]
        for part, rows, cols in box_chunks(rays, self.hulls):
            dx, dy = rays.dx[cols], rays.dy[rows]
            a = self.axis[part]
            sd = a[:, 0] * dx + a[:, 1] * dy + a[:, 2]
            k = self.slope[part]
            quad_a = dx * dx + dy * dy + 1.0 - (1.0 + k * k) * sd * sd
            w = w0[part]
            half_b = w[:, 0] * dx + w[:, 1] * dy + w[:, 2] - beta[part] * sd
            disc = half_b * half_b - quad_a * c[part]
            sel = np.flatnonzero(disc >= 0.0)
            if sel.size == 0:
                continue
            part, rows, cols, sd, quad_a, half_b = part[sel], rows[sel], cols[sel], sd[sel], quad_a[sel], half_b[sel]
            root = np.sqrt(disc[sel])
            best = np.full(sel.size, np.inf)
            s_start, lo, hi = s0[part], self.s_lo[part], self.s_hi[part]
            with np.errstate(divide="ignore", invalid="ignore"):
                for t in ((-half_b - root) / quad_a, (-half_b + root) / quad_a):
                    s = s_start + t * sd
                    best = np.where((t > NEAR_M) & (s >= lo) & (s <= hi) & (t < best), t, best)
                capped = np.flatnonzero(self.capped[part])
                if capped.size:
                    best[capped] = np.minimum(
                        best[capped],
                        self._cap_depth(
                            part[capped],
                            w0[part[capped]],
                            rays.dx[cols[capped]],
                            rays.dy[rows[capped]],
                            sd[capped],
                            s_start[capped],
                        ),
                    )
            index = rows * width + cols
            keep = np.flatnonzero(best < depth.ravel()[index])
            if keep.size:
                yield nearest_per_sample(index[keep], best[keep], part[keep])

    def _cap_depth(
        self, part: np.ndarray, w0: np.ndarray, dx: np.ndarray, dy: np.ndarray, sd: np.ndarray, s0: np.ndarray
    ) -> np.ndarray:
        """Depth of the flat tip caps along the given rays (inf off the disc)."""
        length = self.length[part]
        t = (length - s0) / sd
        rel = w0 + t[:, None] * np.stack([dx, dy, np.ones_like(dx)], axis=1)
        radial2 = norm3(rel) ** 2 - length**2
        return np.where((t > NEAR_M) & (radial2 <= self.r1[part] ** 2), t, np.inf)

    def shade(self, points: np.ndarray, part: np.ndarray, light: Lighting, sample_angle: float) -> np.ndarray:
        """Batch protocol: RGB `(N, 3)` of hit `points` `(N, 3)` on the given parts under `light`."""
        axis, k = self.axis[part], self.slope[part]
        rel = points - self.base[part]
        s = rowdot(rel, axis)
        radial = rel - s[:, None] * axis
        dist = np.maximum(norm3(radial), 1e-12)
        radial_unit = radial / dist[:, None]
        normals = (radial_unit - k[:, None] * axis) / np.sqrt(1.0 + k * k)[:, None]
        on_cap = (s >= self.length[part] - 1e-9) & (dist < (self.r0[part] + k * s) * (1 - 1e-6))
        normals[on_cap] = axis[on_cap]
        theta = np.arctan2(rowdot(radial_unit, self.e2[part]), rowdot(radial_unit, self.e1[part]))
        u = s / self.along_m[part] * TILE_SIZE
        v = (theta + np.pi) / (2 * np.pi) * self.around[part] * TILE_SIZE
        texel_m = np.minimum(self.along_m[part], 2 * np.pi * (self.r0[part] + k * s) / self.around[part]) / TILE_SIZE
        footprint = light.footprint_m(points, normals, sample_angle) / np.maximum(texel_m, 1e-9)
        albedo = np.empty((part.size, 3), dtype=np.float32)
        tile_of = self.tile_index[part]
        for index, tile in enumerate(self.tiles):
            sel = np.flatnonzero(tile_of == index)
            if sel.size:
                albedo[sel] = tile.sample(u[sel], v[sel], footprint[sel])
        return albedo * self.tint[part] * light.diffuse(normals)
