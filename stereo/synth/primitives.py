"""What every ray-cast surface shares: vector helpers, the light, hit records and the batch protocol.

All geometry is in the left camera frame (metres, x right, y down, z forward). A ray from
`origin` with direction `(dx, dy, 1)` reaches depth Z at parameter t = Z, so hits are recorded
as depths directly. Surfaces are cast in *batches* (all cones, all leaves, one plane): each
primitive of a batch tests only the samples inside its own image box, and the batch returns,
per sample, its nearest hit. Each surface colours a hit from the hit point's own surface
coordinates (see `textures`), which is what makes the two views agree.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from stereo.synth.camera import RayGrid, enumerate_boxes

NEAR_M = 1e-3
#: Hits beyond this depth (m) count as sky: the ground near the horizon, like UE5 depth, saturates there.
FAR_M = 500.0
#: Samples per chunk of box samples cast at once (bounds memory to a few hundred MB).
CHUNK_SAMPLES = 1 << 20


def unit(vector: np.ndarray) -> np.ndarray:
    """`vector` scaled to length 1."""
    vector = np.asarray(vector, dtype=np.float64)
    return vector / np.sqrt(vector @ vector)


def dot3(vectors: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise dot products of `(N, 3)` vectors with one 3-vector `(3,)` (no BLAS: it is slow for 3 columns)."""
    return vectors[:, 0] * v[0] + vectors[:, 1] * v[1] + vectors[:, 2] * v[2]


def rowdot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products `(N,)` of two `(N, 3)` arrays."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of 3-vectors or of `(N, 3)` rows (numpy's `cross` is slow on tiny arrays)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def norm3(vectors: np.ndarray) -> np.ndarray:
    """Row-wise lengths `(N,)` of `(N, 3)` vectors."""
    return np.sqrt(vectors[:, 0] ** 2 + vectors[:, 1] ** 2 + vectors[:, 2] ** 2)


@dataclass(frozen=True)
class Lighting:
    """A directional sun plus ambient light and distance haze; vectors in the camera frame."""

    sun_direction: np.ndarray
    sun_rgb: np.ndarray
    ambient_rgb: np.ndarray
    haze_rgb: np.ndarray
    haze_distance_m: float

    def diffuse(self, normals: np.ndarray, two_sided: bool = False) -> np.ndarray:
        """Light `(N, 3)` reaching surfaces with unit `normals` `(N, 3)` (Lambert + ambient)."""
        cosine = dot3(normals, self.sun_direction)
        cosine = np.abs(cosine) if two_sided else np.maximum(cosine, 0.0)
        return self.ambient_rgb[None, :] + cosine[:, None] * self.sun_rgb[None, :]

    def footprint_m(self, points: np.ndarray, normals: np.ndarray, sample_angle: float) -> np.ndarray:
        """Size (m) of one image sample on the surface at `points` `(N, 3)` seen from the left camera.

        `sample_angle` is the angle one sample subtends (rad, 1/(f·samples)); obliquity, from the
        unit `normals`, stretches it (capped at 5×). Both views use the left camera's value.
        """
        distance = norm3(points)
        cosine = np.abs(rowdot(points, normals)) / np.maximum(distance, 1e-9)
        return distance * sample_angle / np.maximum(cosine, 0.2)

    def hazed(self, colour: np.ndarray, points: np.ndarray) -> np.ndarray:
        """`colour` `(N, 3)` blended toward the haze colour with distance of `points` `(N, 3)` from the rig."""
        weight = 1.0 - np.exp(-norm3(points) / self.haze_distance_m)
        return colour + (self.haze_rgb[None, :] - colour) * weight[:, None]


def unit_rows(vectors: np.ndarray) -> np.ndarray:
    """`(N, 3)` vectors scaled to length 1."""
    return vectors / norm3(vectors)[:, None]


def perpendicular_frames(axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors `(K, 3)` each completing unit `axes` `(K, 3)` to right-handed orthonormal frames."""
    helper = np.where((np.abs(axes[:, 2]) < 0.9)[:, None], [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = unit_rows(cross3(axes, helper))
    return e1, cross3(axes, e1)


@dataclass(frozen=True)
class Hits:
    """Nearest hits of a batch on some samples: flat sample index (`row·W + col`), depth (m), part index."""

    index: np.ndarray
    depth: np.ndarray
    part: np.ndarray


class Batch(Protocol):
    """A group of surfaces cast together."""

    def hits(self, rays: RayGrid, depth: np.ndarray) -> Iterator[Hits]:
        """Hits nearer than the current `depth` buffer (`Hs×Ws`, m), chunk by chunk; the caller writes each chunk."""

    def instance_ids(self, part: np.ndarray) -> np.ndarray:
        """Mask ids (uint16) of the given parts."""

    def shade(self, points: np.ndarray, part: np.ndarray, light: Lighting, sample_angle: float) -> np.ndarray:
        """RGB `(N, 3)` (about [0, 1]) of hit `points` `(N, 3)` on the given parts under `light`.

        `sample_angle` (rad per image sample) sets how much the texture is filtered.
        """


def nearest_per_sample(index: np.ndarray, depth: np.ndarray, part: np.ndarray) -> Hits:
    """Keep, for every sample index, only the hit with the smallest depth."""
    order = np.lexsort((depth, index))
    index, depth, part = index[order], depth[order], part[order]
    first = np.ones(index.size, dtype=bool)
    first[1:] = index[1:] != index[:-1]
    return Hits(index[first], depth[first], part[first])


def box_chunks(rays: RayGrid, hulls: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Flat `(part, row, col)` samples of the primitives' image boxes, about `CHUNK_SAMPLES` at a time.

    `hulls` `(K, M, 3)`; primitives keep their order, so sorting them near-to-far lets later
    chunks be culled by the depth buffer the earlier ones filled.
    """
    r0, r1, c0, c1 = rays.sample_boxes(hulls)
    sizes = (r1 - r0) * (c1 - c0)
    start = 0
    while start < sizes.size:
        stop = start + max(1, int(np.searchsorted(np.cumsum(sizes[start:]), CHUNK_SAMPLES, side="right")))
        part, rows, cols = enumerate_boxes(r0[start:stop], r1[start:stop], c0[start:stop], c1[start:stop])
        if part.size:
            yield part + start, rows, cols
        start = stop
