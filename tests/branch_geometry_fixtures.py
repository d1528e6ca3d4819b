"""Exact little scenes for cut-point tests: cylinders ray-cast into a disparity map and instance mask.

Independent of the synthetic scene generator so the geometry is tested against numbers computed
here from first principles: a ray through each pixel is intersected with finite cylinders, the
nearest hit wins (z-buffer), disparity = f·B/Z.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from branchrange.core.geometry import StereoGeometry


@dataclass(frozen=True)
class Cylinder:
    """A finite cylinder from `start` (3,) along unit `direction` for `length` metres, radius `radius`."""

    start: np.ndarray
    direction: np.ndarray
    length: float
    radius: float

    def point(self, t: float) -> np.ndarray:
        """Axis point `t` metres from the start."""
        return np.asarray(self.start, float) + t * np.asarray(self.direction, float)


def unit(v) -> np.ndarray:
    """v / |v| as float64."""
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


@dataclass
class CylinderScene:
    """Disparity (`float32` H×W, 0 where nothing is hit) and instance labels (`int32` H×W)."""

    geometry: StereoGeometry
    disparity: np.ndarray
    labels: np.ndarray
    depth: np.ndarray
    parts: dict[int, list[Cylinder]] = field(default_factory=dict)


def ray_cast(width: int, height: int, geometry: StereoGeometry, parts: dict[int, list[Cylinder]]) -> CylinderScene:
    """Render `parts` (label → cylinders) seen from the left camera; nearest surface wins."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays = np.stack(
        [(u - geometry.cx) / geometry.focal_px, (v - geometry.cy) / geometry.focal_px, np.ones_like(u)], axis=-1
    )
    depth = np.full((height, width), np.inf)
    labels = np.zeros((height, width), dtype=np.int32)
    for label, cylinders in parts.items():
        for cyl in cylinders:
            a = unit(cyl.direction)
            p0 = np.asarray(cyl.start, dtype=np.float64)
            d_perp = rays - (rays @ a)[..., None] * a
            w = -p0
            w_perp = w - (w @ a) * a
            qa = np.einsum("hwc,hwc->hw", d_perp, d_perp)
            qb = d_perp @ w_perp
            qc = w_perp @ w_perp - cyl.radius**2
            disc = qb**2 - qa * qc
            hit = (disc >= 0) & (qa > 1e-12)
            s = np.where(hit, (-qb - np.sqrt(np.maximum(disc, 0))) / np.maximum(qa, 1e-12), 0.0)
            t_axis = (s[..., None] * rays - p0) @ a
            hit &= (s > 0) & (t_axis >= 0) & (t_axis <= cyl.length)
            z = np.where(hit, s, np.inf)  # rays have z = 1, so the ray parameter is the depth
            nearer = z < depth
            depth[nearer] = z[nearer]
            labels[nearer] = label
    disparity = np.where(np.isfinite(depth), geometry.fb / depth, 0.0).astype(np.float32)
    return CylinderScene(geometry, disparity, labels, depth.astype(np.float32), parts)


GEOMETRY = StereoGeometry(focal_px=500.0, baseline_m=0.063, cx=159.5, cy=119.5)
TRUNK_LABEL = 100


def branch_with_trunk(
    direction=(1.0, -0.3, -0.4), radius=0.015, length=0.45, trunk=True, width=320, height=240
) -> tuple[CylinderScene, np.ndarray, np.ndarray]:
    """A vertical trunk at 1.5 m and one branch leaving its surface; returns (scene, base, direction).

    The base is where the branch axis leaves the trunk surface (metres, camera frame).
    """
    trunk_axis_x, trunk_z, trunk_r = -0.35, 1.5, 0.08
    direction = unit(direction)
    base = np.array([trunk_axis_x, 0.05, trunk_z]) + trunk_r * unit([direction[0], 0, direction[2]])
    parts = {1: [Cylinder(base, direction, length, radius)]}
    if trunk:
        parts[TRUNK_LABEL] = [Cylinder(np.array([trunk_axis_x, -1.0, trunk_z]), unit([0, 1, 0]), 2.0, trunk_r)]
    return ray_cast(width, height, GEOMETRY, parts), base, direction
