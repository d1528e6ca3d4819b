"""The MAVLink 2 messages BranchRange sends, built from what one send reports (`FrameTargets`).

`FrameTargets` holds the target cut point and the obstacles in body FRD metres *at the moment of
sending*: from a `branchrange/v1` result through the mount alone (`targets_from_result`, no
vehicle state) or from world tracks re-expressed in the newest pose (the relay). One send gives,
all stamped with the same `time_boot_ms`:
- DISTANCE_SENSOR (132): distance from the camera to the target cut point in centimetres, and its
  confidence as `signal_quality` (see `signal_quality`); no target → `current_distance = max_distance + 1`
  (the MAVLink "nothing in range" value) and `signal_quality` 0 (unknown). The only confidence the
  autopilot gets: OBSTACLE_DISTANCE_3D and DEBUG_VECT have no field for one.
- OBSTACLE_DISTANCE_3D (11037, ardupilotmega): one per cut point, body FRD (frame 12), metres,
  `obstacle_id` = branch id. ArduPilot starts a new obstacle set when `time_boot_ms` changes and
  ignores points outside [min, max]: a frame with nothing to report sends one point beyond
  `max_distance` (id 65535), which clears the old set and keeps the sensor healthy.
- DEBUG_VECT (250) "CUT": the target cut point in body FRD metres (NaN when there is none), for
  PX4 (which has no 3D obstacle message) and for flight logs.

The target branch goes into OBSTACLE_DISTANCE_3D only with `target_as_obstacle`, and never a second
time under another id: a cut point within `duplicate_radius_m` of the target is the target seen
twice (a second mask instance or track of the same branch). Cut points with a confidence below
`obstacle_min_confidence` are not obstacles (a 5 mm twig misplaced by 1.7 m must not fence the
drone off). ArduPilot's
MAVLink proximity backend also files DISTANCE_SENSOR readings whose orientation is one of the
eight horizontal directions into its fence (AP_Proximity_MAV::handle_distance_sensor_msg), so
unless the target is meant to be an obstacle, DISTANCE_SENSOR carries orientation CUSTOM (100)
with the mount quaternion: rangefinder consumers and logs still read it, the fence does not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from branchrange.config.sections import MavlinkConfig
from branchrange.core.frame_result import FrameResult
from branchrange.onboard.mavlink.frames import MAV_SENSOR_ROTATION_CUSTOM, CameraMount

#: obstacle_id of the out-of-range point that clears ArduPilot's obstacle set.
NO_OBSTACLE_ID = 65535
DEBUG_VECT_NAME = b"CUT"
#: SET_POSITION_TARGET_LOCAL_NED type_mask: position and yaw used; velocity, acceleration, yaw rate ignored.
POSITION_AND_YAW_MASK = (
    mavlink2.POSITION_TARGET_TYPEMASK_VX_IGNORE
    | mavlink2.POSITION_TARGET_TYPEMASK_VY_IGNORE
    | mavlink2.POSITION_TARGET_TYPEMASK_VZ_IGNORE
    | mavlink2.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink2.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | mavlink2.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | mavlink2.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
)
MAV_CMD_SET_MESSAGE_INTERVAL = 511


@dataclass(frozen=True)
class BodyPoint:
    """A cut point in body FRD metres (`body_m`, shape (3,)) with its id and confidence in [0, 1]."""

    id: int
    body_m: np.ndarray
    confidence: float = 1.0


@dataclass(frozen=True)
class FrameTargets:
    """What one send reports: the target (or None) and the obstacle candidates, body FRD."""

    target: BodyPoint | None
    candidates: list[BodyPoint]


def heartbeat(camera_lost: bool) -> mavlink2.MAVLink_heartbeat_message:
    """HEARTBEAT of an onboard computer: status CRITICAL while the camera is lost, else ACTIVE."""
    status = mavlink2.MAV_STATE_CRITICAL if camera_lost else mavlink2.MAV_STATE_ACTIVE
    return mavlink2.MAVLink_heartbeat_message(
        mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, status, 3
    )


def targets_from_result(result: FrameResult | None, mount: CameraMount) -> FrameTargets:
    """A result's cut points in body FRD through the mount (the frame of their capture)."""
    if result is None:
        return FrameTargets(None, [])
    points = [BodyPoint(b.id, mount.to_body(b.cut_point_m), b.confidence) for b in result.branches]
    return FrameTargets(next((p for p in points if p.id == result.target_id), None), points)


def obstacles(targets: FrameTargets, cfg: MavlinkConfig, duplicate_radius_m: float) -> list[BodyPoint]:
    """The candidates that go out as obstacles: confident, and not the target (unless configured)."""
    chosen = []
    for p in targets.candidates:
        if p.confidence < cfg.obstacle_min_confidence:
            continue
        if targets.target is not None and (
            p.id == targets.target.id or float(np.linalg.norm(p.body_m - targets.target.body_m)) < duplicate_radius_m
        ):
            continue
        chosen.append(p)
    if cfg.target_as_obstacle and targets.target is not None:
        chosen.insert(0, targets.target)
    return chosen


def signal_quality(target: BodyPoint | None) -> int:
    """DISTANCE_SENSOR.signal_quality (uint8, %) of a target: its confidence in [0, 1] as 1..100, rounded and
    never below 1, since MAVLink reads 0 as "unknown" and a confidence was measured (1 is MAVLink's "invalid
    signal", ArduPilot's worst quality: a confidence under 1.5 %); 0 without a target (nothing was measured)."""
    if target is None:
        return 0
    return min(100, max(1, round(target.confidence * 100)))


def distance_sensor(
    target: BodyPoint | None, mount: CameraMount, cfg: MavlinkConfig, time_boot_ms: int
) -> mavlink2.MAVLink_distance_sensor_message:
    """DISTANCE_SENSOR for the target (camera → cut point, cm; its confidence as signal_quality), or "nothing in
    range"."""
    max_cm = round(cfg.max_distance_m * 100)
    if target is None:
        current_cm = max_cm + 1
    else:
        current_cm = min(round(float(np.linalg.norm(target.body_m - mount.translation_m)) * 100), 65534)
    if cfg.target_as_obstacle:
        orientation = mount.sensor_orientation()
    else:
        orientation = MAV_SENSOR_ROTATION_CUSTOM
    quaternion = mount.quaternion_wxyz if orientation == MAV_SENSOR_ROTATION_CUSTOM else (0.0, 0.0, 0.0, 0.0)
    return mavlink2.MAVLink_distance_sensor_message(
        time_boot_ms,
        round(cfg.min_distance_m * 100),
        max_cm,
        current_cm,
        mavlink2.MAV_DISTANCE_SENSOR_UNKNOWN,
        cfg.sensor_id,
        orientation,
        255,
        0.0,
        0.0,
        quaternion,
        signal_quality(target),
    )


def obstacles_3d(
    points: list[BodyPoint], cfg: MavlinkConfig, time_boot_ms: int
) -> list[mavlink2.MAVLink_obstacle_distance_3d_message]:
    """OBSTACLE_DISTANCE_3D for every obstacle (body FRD), or the out-of-range "none" point."""

    def message(obstacle_id: int, xyz: Any) -> mavlink2.MAVLink_obstacle_distance_3d_message:
        return mavlink2.MAVLink_obstacle_distance_3d_message(
            time_boot_ms,
            mavlink2.MAV_DISTANCE_SENSOR_UNKNOWN,
            mavlink2.MAV_FRAME_BODY_FRD,
            obstacle_id,
            float(xyz[0]),
            float(xyz[1]),
            float(xyz[2]),
            cfg.min_distance_m,
            cfg.max_distance_m,
        )

    if not points:
        return [message(NO_OBSTACLE_ID, (cfg.max_distance_m + 1.0, 0.0, 0.0))]
    return [message(p.id & 0xFFFF, p.body_m) for p in points]


def debug_vect(target: BodyPoint | None, time_boot_ms: int) -> mavlink2.MAVLink_debug_vect_message:
    """DEBUG_VECT "CUT": the target cut point in body FRD metres, NaN when there is no target."""
    xyz = (math.nan,) * 3 if target is None else target.body_m
    return mavlink2.MAVLink_debug_vect_message(
        DEBUG_VECT_NAME, time_boot_ms * 1000, float(xyz[0]), float(xyz[1]), float(xyz[2])
    )


def frame_messages(
    targets: FrameTargets, mount: CameraMount, cfg: MavlinkConfig, time_boot_ms: int, duplicate_radius_m: float
) -> list[mavlink2.MAVLink_message]:
    """All messages of one send, sharing `time_boot_ms`, in sending order."""
    return [
        distance_sensor(targets.target, mount, cfg, time_boot_ms),
        *obstacles_3d(obstacles(targets, cfg, duplicate_radius_m), cfg, time_boot_ms),
        debug_vect(targets.target, time_boot_ms),
    ]


def message_interval_request(
    message_id: int, rate_hz: float, target_system: int, target_component: int
) -> mavlink2.MAVLink_command_long_message:
    """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL: stream `message_id` at `rate_hz`."""
    return mavlink2.MAVLink_command_long_message(
        target_system,
        target_component,
        MAV_CMD_SET_MESSAGE_INTERVAL,
        0,
        float(message_id),
        1e6 / rate_hz,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
    )


def position_target(
    setpoint_ned_m: np.ndarray, yaw_rad: float, time_boot_ms: int, target_system: int, target_component: int
) -> mavlink2.MAVLink_set_position_target_local_ned_message:
    """SET_POSITION_TARGET_LOCAL_NED: fly to `setpoint_ned_m` (3,) m facing `yaw_rad`."""
    x, y, z = (float(v) for v in setpoint_ned_m)
    return mavlink2.MAVLink_set_position_target_local_ned_message(
        time_boot_ms,
        target_system,
        target_component,
        mavlink2.MAV_FRAME_LOCAL_NED,
        POSITION_AND_YAW_MASK,
        x,
        y,
        z,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        float(yaw_rad),
        0.0,
    )
