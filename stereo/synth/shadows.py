"""Shadows of the wood on the ground, for the randomized scenes: a low sun draws long stripes across the alley.

The renderer lights each surface by the sun's angle alone (`primitives.Lighting`); it casts no shadow
rays. The ground's shadows matter most to what a segmenter sees (dark stripes that look like branches,
lying across the alley under a low sun), and they are cheap: every cone's axis is projected along the
sun's rays onto the ground plane and drawn, as wide as the cone, into a raster in ground coordinates;
the ground then loses the sun's share of its light where the raster says it is shaded. Leaves and the
wood's shadows on itself are not drawn.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import cv2
import numpy as np

from stereo.synth.cones import Cone
from stereo.synth.planes import PlaneLayer
from stereo.synth.primitives import Lighting, dot3

#: size (m) of one shadow raster cell, and how far (m) the raster reaches across and ahead on the ground
CELL_M = 0.02
REACH_M = 24.0


@dataclass(frozen=True)
class GroundShadow:
    """Shadow coverage of a ground plane: `coverage` float32 `R×C` in [0, 1] (1: the sun is hidden), cell
    (r, c) covering plane coordinates u = u0 + c·cell, v = v0 + r·cell (m)."""

    coverage: np.ndarray
    u0: float
    v0: float
    cell_m: float

    def at(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Coverage `(N,)` at plane coordinates `u`, `v` `(N,)` (m); 0 outside the raster."""
        cols, rows = (u - self.u0) / self.cell_m, (v - self.v0) / self.cell_m
        height, width = self.coverage.shape
        inside = (cols >= 0) & (cols < width - 1) & (rows >= 0) & (rows < height - 1)
        c, r = np.where(inside, cols, 0.0), np.where(inside, rows, 0.0)
        c0, r0 = c.astype(np.int64), r.astype(np.int64)
        fc, fr = c - c0, r - r0
        grid = self.coverage
        top = grid[r0, c0] * (1 - fc) + grid[r0, c0 + 1] * fc
        bottom = grid[r0 + 1, c0] * (1 - fc) + grid[r0 + 1, c0 + 1] * fc
        return np.asarray(np.where(inside, top * (1 - fr) + bottom * fr, 0.0), dtype=np.float32)


def cast_on_ground(cones: Sequence[Cone], ground: PlaneLayer, sun_direction: np.ndarray) -> GroundShadow | None:
    """The shadow the `cones` (camera frame) cast on `ground` under a sun along unit `sun_direction` (toward the
    sun, camera frame); None when the sun is at or below the ground's horizon."""
    normal = ground.normal
    facing = float(sun_direction @ normal)
    if facing <= 0.02:
        return None
    size = int(2 * REACH_M / CELL_M)
    raster = np.zeros((size, size), dtype=np.uint8)
    u0 = v0 = -REACH_M

    def on_ground(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raster (col, row) of `points` `(N, 3)` carried along the sun's rays onto the plane, and whether they
        are above it."""
        height = dot3(points - ground.point, normal)
        landed = points - (height / facing)[:, None] * sun_direction[None, :]
        rel = landed - ground.point
        # a trunk's foot sits on the ground, a little below it counts too
        return np.stack([(dot3(rel, ground.eu) - u0) / CELL_M, (dot3(rel, ground.ev) - v0) / CELL_M], 1), height > -0.1

    starts = np.array([c.base for c in cones]).reshape(-1, 3)
    ends = starts + np.array([c.length * c.axis for c in cones]).reshape(-1, 3)
    (a, above_a), (b, above_b) = on_ground(starts), on_ground(ends)
    widths = np.array([2 * max(c.r0, c.r1) / CELL_M for c in cones])
    inside = np.all((np.abs(np.concatenate([a, b], 1) - size / 2) < 4 * size), axis=1)
    for k in np.flatnonzero(above_a & above_b & inside):
        start, end = (tuple(int(round(x)) for x in p) for p in (a[k], b[k]))
        cv2.line(raster, start, end, 255, max(1, int(round(widths[k]))), cv2.LINE_AA)
    coverage = cv2.GaussianBlur(raster.astype(np.float32) / 255.0, (0, 0), 1.0)  # a little penumbra
    return GroundShadow(coverage, u0, v0, CELL_M)


@dataclass(frozen=True)
class ShadowedPlane(PlaneLayer):
    """A `PlaneLayer` that loses the sun's share of its light where `shadow` covers it (None: no shadow)."""

    shadow: GroundShadow | None = None

    @classmethod
    def of(cls, plane: PlaneLayer, shadow: GroundShadow | None) -> ShadowedPlane:
        """`plane` with `shadow`."""
        return cls(**{f.name: getattr(plane, f.name) for f in fields(PlaneLayer)}, shadow=shadow)

    def shade(self, points: np.ndarray, part: np.ndarray, light: Lighting, sample_angle: float) -> np.ndarray:
        """Batch protocol: the plane's colour with the sun's term scaled by 1 − coverage, per channel."""
        lit = super().shade(points, part, light, sample_angle)
        if self.shadow is None:
            return lit
        rel = points - self.point
        coverage = self.shadow.at(dot3(rel, self.eu), dot3(rel, self.ev))
        sun = self.light_factor * light.sun_rgb
        share = sun / np.maximum(light.ambient_rgb + sun, 1e-6)  # the sun's part of the light on the plane
        return np.asarray(lit * (1.0 - coverage[:, None] * share[None, :]), dtype=np.float32)
