"""Cut points where the camera sees in perspective: near, thick trunks off the optical axis, and
silhouettes the image border cuts — against exactly ray-cast cylinders."""

from __future__ import annotations

import numpy as np
import pytest
from branch_geometry_fixtures import TRUNK_LABEL, Cylinder, ray_cast, unit

from branchrange.core.cutpoints import CutPointConfig, estimate_cut_points, fit_trunk
from branchrange.core.cylinder_section import cross_section, radius_from_silhouette
from branchrange.core.geometry import GeometryError, Line3D, StereoGeometry
from branchrange.core.masks import masks_from_array
from branchrange.core.silhouette import image_axis

#: The synthetic generator's rig at 640×360 (f = 320 px, principal point at the image centre).
WIDE = StereoGeometry(focal_px=320.0, baseline_m=0.063, cx=319.5, cy=179.5)
#: A trunk 36 cm thick, 1.4 m away and 33° to the left: its silhouette's pixel mid-point lies
#: about 1.6 cm beside the axis's image, which a near-orthographic model takes for the axis.
#: Leaning 3° like the generator's trunks, so the pixel grid does not quantise every row alike.
TRUNK_AXIS_POINT, TRUNK_RADIUS, TRUNK_AXIS = np.array([-0.77, 0.0, 1.18]), 0.18, unit([0.045, 1.0, 0.02])


def trunk_and_branch(direction):
    """The trunk above and a branch leaving its surface along `direction`; (scene, base, unit direction)."""
    direction = unit(direction)
    across = direction - (direction @ TRUNK_AXIS) * TRUNK_AXIS
    base = TRUNK_AXIS_POINT + direction * TRUNK_RADIUS / np.linalg.norm(across)
    parts = {
        TRUNK_LABEL: [Cylinder(TRUNK_AXIS_POINT - 1.5 * TRUNK_AXIS, TRUNK_AXIS, 3.0, TRUNK_RADIUS)],
        1: [Cylinder(base, direction, 0.5, 0.012)],
    }
    return ray_cast(640, 360, WIDE, parts), base, direction


def test_thick_trunk_off_the_optical_axis_is_fitted_on_its_axis_with_its_radius():
    scene, _, _ = trunk_and_branch((1.0, -0.3, -0.5))
    model = fit_trunk(scene.labels == TRUNK_LABEL, scene.disparity, WIDE, CutPointConfig())
    axis = model.cylinder.axis
    foot = axis.at(axis.parameters(TRUNK_AXIS_POINT[None])[0])
    assert np.linalg.norm(foot - TRUNK_AXIS_POINT) < 0.003
    assert abs(axis.direction @ TRUNK_AXIS) > 0.9999
    assert model.cylinder.radius_at(foot, WIDE) == pytest.approx(TRUNK_RADIUS, abs=0.002)


@pytest.mark.parametrize("direction", [(1.0, -0.3, -0.5), (1.0, 0.2, 0.4), (0.6, -0.8, -0.3)])
def test_cut_point_at_a_thick_off_axis_trunk_within_half_a_centimetre(direction):
    scene, base, d = trunk_and_branch(direction)
    masks = masks_from_array(scene.labels, trunk_id=TRUNK_LABEL, kind="instance")
    [b] = estimate_cut_points(masks, scene.disparity, WIDE).branches
    assert np.linalg.norm(b.base_m - base) < 0.005
    assert np.linalg.norm(b.cut_point_m - (base + CutPointConfig().cut_offset_m * d)) < 0.005
    assert b.diameter_m == pytest.approx(0.024, rel=0.1)


def test_cross_section_recovers_axis_and_radius_from_one_row_to_within_its_pixel_quantisation():
    """One row of a vertical trunk: its edges are known to ±½ px, 2.2 mm at 1.4 m."""
    axis = Line3D(TRUNK_AXIS_POINT, unit([0, 1, 0]))
    scene = ray_cast(
        640, 360, WIDE, {1: [Cylinder(TRUNK_AXIS_POINT + [0, -1.0, 0], axis.direction, 2.0, TRUNK_RADIUS)]}
    )
    row = 180
    cols = np.nonzero(scene.labels[row] == 1)[0]
    # edges half a pixel beyond the outermost pixel centres; mean disparity of all but one pixel each side
    left, right = cols.min() - 0.5, cols.max() + 0.5
    centre, half_width = np.array([(left + right) / 2, row]), (right - left) / 2
    mean_disparity = float(scene.disparity[row, cols[1:-1]].mean())
    section = cross_section(centre, np.array([1.0, 0.0]), half_width, 1.0, mean_disparity, axis.direction, WIDE)
    assert np.linalg.norm(section.axis_point_m - axis.at(axis.parameters(section.axis_point_m[None])[0])) < 0.005
    assert section.radius_m == pytest.approx(TRUNK_RADIUS, abs=0.0025)
    assert radius_from_silhouette(centre, np.array([1.0, 0.0]), half_width, axis, WIDE) == pytest.approx(
        TRUNK_RADIUS, abs=0.0025
    )


def test_cross_section_of_an_axis_along_the_line_of_sight_is_refused():
    toward_camera = unit([-0.77, 0.0, 1.18])
    with pytest.raises(GeometryError, match="viewing ray|do not bound a cylinder"):
        cross_section(np.array([110.0, 179.5]), np.array([1.0, 0.0]), 50.0, 1.0, 17.0, toward_camera, WIDE)


def test_border_cut_silhouette_takes_its_direction_from_its_sides_not_its_diagonal():
    # a band 16 px wide at 37° to the rows, cut by the left image border and by a trunk's straight edge
    v, u = np.mgrid[0:360, 0:640].astype(np.float64)
    along = np.array([0.8, -0.6])
    normal = np.array([0.6, 0.8])
    band = np.abs((u - 0.0) * normal[0] + (v - 250.0) * normal[1]) < 8.0
    trunk = u >= 30
    mask = band & ~trunk
    silhouette = image_axis(mask, cut_by=trunk)
    assert abs(silhouette.direction @ along) > np.cos(np.radians(2.0))
    principal = image_axis(mask)  # without knowing the trunk's cut, its edge pulls the direction off
    assert abs(principal.direction @ along) < abs(silhouette.direction @ along)
