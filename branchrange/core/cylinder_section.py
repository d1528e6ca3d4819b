"""Where a cylinder's axis lies, from one cross-section of its silhouette and the disparity across it.

Why not the silhouette's mid-point pushed back by a fixed share of the radius: a near, thick
cylinder off the optical axis (a trunk 20 cm thick at 1.4 m, 30° to the side) is seen in
perspective. Its image is wider on the side away from the image centre, so the pixel mid-point
of the silhouette lies up to 2 cm beside the axis's image, and the visible front's mean depth is
not a fixed fraction of the radius in front of the axis.

Exact model, local to one station along the silhouette: the silhouette's two edges are the
images of two planes through the camera centre, both tangent to the cylinder. Seen along the
axis direction `a`, the camera is a point, the cylinder a circle, and the two edge rays are the
tangents from the point to the circle: the circle's centre lies on their bisector, at a distance
`D` with `r = D·sin β` (β = half the angle between the tangents). Everything scales with `D`,
so the mean disparity of the visible surface across the (eroded) silhouette is `f·B/D` times a
number computed here by casting the pixels' rays at the unit-distance circle — and the measured
mean disparity gives `D`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from branchrange.core.geometry import GeometryError, Line3D, StereoGeometry, pixel_ray, pixel_rays, vector_norm

#: Rays cast across the silhouette per station to integrate the visible surface's disparity.
SECTION_SAMPLES = 65


@dataclass(frozen=True)
class CrossSection:
    """A cylinder's axis point at one station (`axis_point_m` (3,), metres, rectified left camera
    frame; the axis point nearest the viewing ray of the silhouette's centre pixel) and its radius (m)."""

    axis_point_m: np.ndarray
    radius_m: float


def _across_axis(rays: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit rays `(N, 3)` seen along `direction`: their unit components across it `(N, 3)` and
    those components' lengths `(N,)` (metres across per metre along the ray)."""
    across = rays - (rays @ direction)[:, None] * direction
    lengths = np.linalg.norm(across, axis=1)
    if np.any(lengths < 1e-6):
        raise GeometryError("the cylinder's axis runs along a viewing ray: no cross-section to measure")
    return across / lengths[:, None], lengths


def _edge_rays(
    centre_px: np.ndarray, normal_px: np.ndarray, half_width_px: float, geometry: StereoGeometry
) -> np.ndarray:
    """The unit viewing rays `(2, 3)` through the silhouette's two edges at one station."""
    if half_width_px <= 0:
        raise GeometryError(f"cross-section needs a silhouette of positive width, got half width {half_width_px} px")
    return pixel_rays(centre_px[None, :] + np.array([[-1.0], [1.0]]) * half_width_px * normal_px[None, :], geometry)


def _tangents(edges: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, float]:
    """The unit bisector `(3,)` of the edge rays `(2, 3)` seen along `direction`, and sin β."""
    (tangent_a, tangent_b), _ = _across_axis(edges, direction)
    bisector = tangent_a + tangent_b
    sin_beta = 0.5 * vector_norm(tangent_a - tangent_b)
    if vector_norm(bisector) < 1e-9 or sin_beta < 1e-9:
        raise GeometryError("the silhouette's edges do not bound a cylinder (zero or opposite tangent directions)")
    return bisector / vector_norm(bisector), sin_beta


def radius_from_silhouette(
    centre_px: np.ndarray, normal_px: np.ndarray, half_width_px: float, axis: Line3D, geometry: StereoGeometry
) -> float:
    """Radius (m) of a cylinder with a known `axis` (metres) whose silhouette at one station is
    `centre_px ± half_width_px · normal_px` (px): `r = D·sin β`, D the camera's distance from the axis."""
    edges = _edge_rays(
        np.asarray(centre_px, dtype=np.float64), np.asarray(normal_px, dtype=np.float64), half_width_px, geometry
    )
    _, sin_beta = _tangents(edges, axis.direction)
    return vector_norm(axis.point - (axis.point @ axis.direction) * axis.direction) * sin_beta


@dataclass(frozen=True)
class SectionRays:
    """The viewing rays of one station of a silhouette, unit `(·, 3)`: through its two edges
    (`edges` `(2, 3)`), through the pixels the disparity was read from (`samples` `(M, 3)`) and
    through its centre (`centre` `(3,)`). They do not depend on the axis direction, so the passes
    that refine the direction reuse them (`section_rays`, then `cross_section_from_rays`)."""

    edges: np.ndarray
    samples: np.ndarray
    centre: np.ndarray


def section_rays(
    centre_px: np.ndarray, normal_px: np.ndarray, half_width_px: float, margin_px: float, geometry: StereoGeometry
) -> SectionRays:
    """`SectionRays` of the station `centre_px ± half_width_px · normal_px` (px), the samples
    spread over the part more than `margin_px` inside the edges (`SECTION_SAMPLES` of them)."""
    centre_px, normal_px = np.asarray(centre_px, dtype=np.float64), np.asarray(normal_px, dtype=np.float64)
    edges = _edge_rays(centre_px, normal_px, half_width_px, geometry)
    reach = max(half_width_px - margin_px, 0.0)
    offsets = np.linspace(-reach, reach, SECTION_SAMPLES) if reach > 0 else np.zeros(1)
    samples = pixel_rays(centre_px[None, :] + offsets[:, None] * normal_px[None, :], geometry)
    return SectionRays(edges, samples, pixel_ray(centre_px[0], centre_px[1], geometry))


def cross_section(
    centre_px: np.ndarray,
    normal_px: np.ndarray,
    half_width_px: float,
    margin_px: float,
    mean_disparity_px: float,
    direction: np.ndarray,
    geometry: StereoGeometry,
) -> CrossSection:
    """The axis point and radius of a cylinder at one station of its silhouette.

    `centre_px` (u, v) is the silhouette's mid-point at the station, `normal_px` the unit image
    direction across the silhouette, `half_width_px` half its width there (px); the disparity
    samples (`mean_disparity_px`, their mean, px) came from the pixels more than `margin_px`
    inside the edges (the mask's erosion). `direction` is the axis's unit direction `(3,)` (the
    cross-section is taken across it). Raises `GeometryError` when the silhouette has no width or
    the axis points at the camera.
    """
    if not mean_disparity_px > 0:
        raise GeometryError(f"cross-section needs a positive disparity, got {mean_disparity_px} px")
    return cross_section_from_rays(
        section_rays(centre_px, normal_px, half_width_px, margin_px, geometry), mean_disparity_px, direction, geometry
    )


def cross_section_from_rays(
    rays: SectionRays, mean_disparity_px: float, direction: np.ndarray, geometry: StereoGeometry
) -> CrossSection:
    """`cross_section` from a station's `SectionRays` (see there)."""
    direction = np.asarray(direction, dtype=np.float64) / vector_norm(direction)
    if not mean_disparity_px > 0:
        raise GeometryError(f"cross-section needs a positive disparity, got {mean_disparity_px} px")
    bisector, sin_beta = _tangents(rays.edges, direction)
    # rays through the (eroded) silhouette, cast at the circle of centre `bisector`, radius sin β (D = 1)
    across, lengths = _across_axis(rays.samples, direction)
    c = across @ bisector
    t_across = c - np.sqrt(np.clip(sin_beta**2 - (1.0 - c * c), 0.0, None))
    depth_at_unit_distance = t_across / lengths * rays.samples[:, 2]
    if np.any(depth_at_unit_distance <= 0):
        raise GeometryError("the cylinder's visible surface reaches behind the camera")
    distance = geometry.fb * float(np.mean(1.0 / depth_at_unit_distance)) / mean_disparity_px
    axis = Line3D(distance * bisector, direction)
    return CrossSection(axis.closest_to_ray(rays.centre), distance * sin_beta)
