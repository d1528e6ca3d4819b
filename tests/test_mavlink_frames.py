"""Camera → body FRD through the mount, and the sensor orientation MAVLink is told."""

from __future__ import annotations

import math

import numpy as np
import pytest

from branchrange.onboard.mavlink.frames import CameraMount, rotation_from_rpy


def test_forward_camera_maps_opencv_axes_to_frd():
    mount = CameraMount.from_rpy()
    # x_frd = z_cam, y_frd = x_cam, z_frd = y_cam
    np.testing.assert_allclose(mount.to_body([0.1, -0.2, 1.4]), [1.4, 0.1, -0.2])
    np.testing.assert_allclose(mount.to_body([[1, 0, 0], [0, 1, 0], [0, 0, 1]]), [[0, 1, 0], [0, 0, 1], [1, 0, 0]])


def test_translation_moves_points_to_the_vehicle_origin():
    mount = CameraMount.from_rpy(xyz_m=(0.15, -0.02, 0.08))
    np.testing.assert_allclose(mount.to_body([0, 0, 2.0]), [2.15, -0.02, 0.08])


def test_camera_pitched_down_sees_a_point_ahead_as_below_the_vehicle():
    mount = CameraMount.from_rpy((0.0, -30.0, 0.0))
    p = mount.to_body([0.0, 0.0, 2.0])  # 2 m along the optical axis
    np.testing.assert_allclose(p, [2 * math.cos(math.radians(30)), 0.0, 2 * math.sin(math.radians(30))], atol=1e-12)


def test_right_looking_camera_puts_its_optical_axis_along_body_y():
    mount = CameraMount.from_rpy((0.0, 0.0, 90.0))
    np.testing.assert_allclose(mount.to_body([0, 0, 1.0]), [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(mount.to_body([1.0, 0, 0]), [-1, 0, 0], atol=1e-12)  # camera right = body back


@pytest.mark.parametrize(
    "rpy, orientation",
    [
        ((0, 0, 0), 0),
        ((0, 0, 45), 1),
        ((0, 0, 90), 2),
        ((0, 0, -90), 6),
        ((0, 0, 180), 4),
        ((0, 90, 0), 24),
        ((0, -90, 0), 25),
        ((0, -30, 0), 100),
        ((20, 0, 0), 0),
        ((0, 3, 0), 0),
    ],
)
def test_sensor_orientation_names_the_standard_direction_or_custom(rpy, orientation):
    assert CameraMount.from_rpy(rpy).sensor_orientation() == orientation


def test_mount_quaternion_rotates_body_x_onto_the_optical_axis():
    mount = CameraMount.from_rpy((10.0, -30.0, 25.0))
    w, x, y, z = mount.quaternion_wxyz
    assert math.isclose(w * w + x * x + y * y + z * z, 1.0)
    # rotation matrix of the quaternion equals the mount rotation
    q_rot = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    np.testing.assert_allclose(q_rot, rotation_from_rpy(10.0, -30.0, 25.0), atol=1e-12)
    assert CameraMount.from_rpy().quaternion_wxyz == (1.0, 0.0, 0.0, 0.0)
