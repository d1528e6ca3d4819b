"""Camera frame → vehicle body frame (FRD) through the configured camera mount.

Camera frame: rectified left camera, OpenCV axes (x right, y down, z forward), metres.
Body frame: FRD (x forward, y right, z down), metres from the vehicle origin. A camera looking
straight ahead maps `x_frd = z_cam, y_frd = x_cam, z_frd = y_cam`; the mount's roll/pitch/yaw
(aerospace Z-Y-X order, degrees) turns that camera, its translation moves its optical centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Camera (OpenCV) axes expressed in FRD for a forward-looking camera: rows are FRD x, y, z.
FORWARD_CAMERA_TO_FRD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

#: MAV_SENSOR_ORIENTATION values a range sensor's axis can have without a custom quaternion:
#: the eight yaw steps of 45° in the horizontal plane, straight up and straight down.
_STANDARD_AXES: dict[int, tuple[float, float, float]] = {
    **{k: (math.cos(math.radians(45 * k)), math.sin(math.radians(45 * k)), 0.0) for k in range(8)},
    24: (0.0, 0.0, -1.0),  # MAV_SENSOR_ROTATION_PITCH_90: up
    25: (0.0, 0.0, 1.0),  # MAV_SENSOR_ROTATION_PITCH_270: down
}
MAV_SENSOR_ROTATION_CUSTOM = 100


def rotation_from_rpy(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """3×3 rotation `Rz(yaw)·Ry(pitch)·Rx(roll)` (aerospace order) from angles in degrees."""
    r, p, y = (math.radians(a) for a in (roll_deg, pitch_deg, yaw_deg))
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


def quaternion_wxyz(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z), w ≥ 0, of a 3×3 rotation matrix."""
    m = rotation
    w = math.sqrt(max(0.0, 1.0 + m[0, 0] + m[1, 1] + m[2, 2])) / 2.0
    x = math.copysign(math.sqrt(max(0.0, 1.0 + m[0, 0] - m[1, 1] - m[2, 2])) / 2.0, m[2, 1] - m[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - m[0, 0] + m[1, 1] - m[2, 2])) / 2.0, m[0, 2] - m[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - m[0, 0] - m[1, 1] + m[2, 2])) / 2.0, m[1, 0] - m[0, 1])
    return (w, x, y, z)


@dataclass(frozen=True)
class CameraMount:
    """Where the camera sits on the vehicle: `turn` (3×3, rotates body FRD vectors of a forward
    camera into the mounted camera's) and `translation_m` (optical centre in body FRD, metres)."""

    turn: np.ndarray
    translation_m: np.ndarray

    @classmethod
    def from_rpy(
        cls, rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0), xyz_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ) -> CameraMount:
        """A mount from roll/pitch/yaw in degrees (0,0,0 = looking forward) and an offset in metres."""
        return cls(rotation_from_rpy(*rpy_deg), np.asarray(xyz_m, dtype=np.float64))

    @property
    def camera_to_body(self) -> np.ndarray:
        """3×3 rotation taking camera-frame (OpenCV) vectors to body FRD vectors."""
        return self.turn @ FORWARD_CAMERA_TO_FRD

    def to_body(self, point_cam_m: np.ndarray | list[float]) -> np.ndarray:
        """Body FRD position (metres, shape (3,) or (N, 3)) of camera-frame points in metres."""
        p = np.asarray(point_cam_m, dtype=np.float64)
        return p @ self.camera_to_body.T + self.translation_m

    @property
    def optical_axis_body(self) -> np.ndarray:
        """Unit vector (3,) of the camera's viewing direction in body FRD."""
        return self.turn[:, 0]

    @property
    def quaternion_wxyz(self) -> tuple[float, float, float, float]:
        """The mount's rotation relative to the body x axis, as DISTANCE_SENSOR's `quaternion`."""
        return quaternion_wxyz(self.turn)

    def sensor_orientation(self, tolerance_deg: float = 5.0) -> int:
        """MAV_SENSOR_ORIENTATION of the optical axis; CUSTOM (100) when no standard one is near."""
        axis = self.optical_axis_body
        for value, standard in _STANDARD_AXES.items():
            if float(axis @ np.asarray(standard)) >= math.cos(math.radians(tolerance_deg)):
                return value
        return MAV_SENSOR_ROTATION_CUSTOM


def skew(v: np.ndarray) -> np.ndarray:
    """3×3 cross-product matrix `[v]×` of a vector (3,)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rotation_exp(rotvec: np.ndarray) -> np.ndarray:
    """3×3 rotation of a rotation vector (3,), radians about its direction (Rodrigues)."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.eye(3) + skew(rotvec)
    k = skew(np.asarray(rotvec, dtype=np.float64) / angle)
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def rotation_log(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector (3,), radians, of a 3×3 rotation with angle below π (inverse of `rotation_exp`)."""
    cos_angle = min(1.0, max(-1.0, (float(np.trace(rotation)) - 1.0) / 2.0))
    angle = math.acos(cos_angle)
    w = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
    if angle < 1e-9:
        return w / 2.0
    return w * (angle / (2.0 * math.sin(angle)))
