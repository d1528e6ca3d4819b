"""Stereo geometry and the robust line fit against numbers computed by hand."""

from __future__ import annotations

import numpy as np
import pytest

from branchrange.core.geometry import (
    GeometryError,
    Line3D,
    StereoGeometry,
    backproject,
    disparity_to_depth,
    fit_line_robust,
    pixel_ray,
    project,
    valid_disparity,
)

GEOM = StereoGeometry(focal_px=700.0, baseline_m=0.063, cx=640.0, cy=360.0)


def test_depth_is_focal_times_baseline_over_disparity():
    disparity = np.array([[44.1, 0.0], [np.nan, 22.05]], dtype=np.float32)
    depth = disparity_to_depth(disparity, GEOM)
    assert depth[0, 0] == pytest.approx(1.0, rel=1e-5)
    assert depth[1, 1] == pytest.approx(2.0, rel=1e-5)
    assert np.isinf(depth[0, 1]) and np.isinf(depth[1, 0])


def test_valid_disparity_excludes_zero_nonfinite_and_beyond_max():
    d = np.array([0.0, -1.0, np.inf, np.nan, 5.0, 191.9, 192.0], dtype=np.float32)
    assert valid_disparity(d, 192).tolist() == [False, False, False, False, True, True, False]


def test_backproject_then_project_round_trips_pixels():
    u, v, d = np.array([100.0, 640.0, 1200.0]), np.array([50.0, 360.0, 700.0]), np.array([10.0, 44.1, 80.0])
    points = backproject(u, v, d, GEOM)
    assert points[1] == pytest.approx([0.0, 0.0, 1.0], abs=1e-9)
    assert points[0, 2] == pytest.approx(GEOM.fb / 10.0)
    np.testing.assert_allclose(project(points, GEOM), np.stack([u, v], axis=1), atol=1e-9)


def test_backproject_refuses_invalid_disparity():
    with pytest.raises(GeometryError, match="finite, positive"):
        backproject(np.array([1.0]), np.array([1.0]), np.array([0.0]), GEOM)


@pytest.mark.parametrize("field,value", [("focal_px", 0.0), ("baseline_m", -0.1), ("cx", float("nan"))])
def test_geometry_rejects_bad_parameters_naming_them(field, value):
    kwargs = dict(focal_px=700.0, baseline_m=0.063, cx=1.0, cy=1.0) | {field: value}
    with pytest.raises(GeometryError, match=field):
        StereoGeometry(**kwargs)


def test_robust_line_fit_ignores_thirty_percent_outliers():
    rng = np.random.default_rng(3)
    direction = np.array([0.6, -0.2, 0.77])
    direction /= np.linalg.norm(direction)
    origin = np.array([0.1, 0.2, 1.5])
    t = rng.uniform(-0.2, 0.2, 700)
    inliers = origin + t[:, None] * direction + rng.normal(0, 0.002, (700, 3))
    outliers = origin + rng.uniform(-0.3, 0.3, (300, 3)) + np.array([0, 0, 0.5])  # background behind
    fit = fit_line_robust(np.vstack([inliers, outliers]), inlier_threshold_m=0.01)
    assert abs(fit.line.direction @ direction) > 0.999
    assert fit.line.distances(origin[None])[0] < 0.002
    assert fit.inliers[:700].mean() > 0.98
    assert fit.inliers[700:].mean() < 0.15
    assert fit.residual_m == pytest.approx(0.002 * np.sqrt(2), rel=0.25)


def test_line_fit_needs_two_distinct_points():
    with pytest.raises(GeometryError, match="2 distinct points"):
        fit_line_robust(np.ones((10, 3)), 0.01)


def test_closest_point_to_ray_lifts_a_pixel_onto_the_line():
    line = Line3D(np.array([0.0, 0.0, 2.0]), np.array([1.0, 0.0, 0.0]))
    target = np.array([0.3, 0.0, 2.0])
    u, v = project(target[None], GEOM)[0]
    np.testing.assert_allclose(line.closest_to_ray(pixel_ray(u, v, GEOM)), target, atol=1e-9)
