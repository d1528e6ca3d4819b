"""The MAVLink 2 messages BranchRange sends, built from one `branchrange/v1` result.

One frame gives, all stamped with the same `time_boot_ms`:
- DISTANCE_SENSOR (132): distance from the camera to the target cut point in centimetres; no
  target → `current_distance = max_distance + 1` (the MAVLink "nothing in range" value).
- OBSTACLE_DISTANCE_3D (11037, ardupilotmega): one per cut point, body FRD (frame 12), metres,
  `obstacle_id` = branch id. ArduPilot starts a new obstacle set when `time_boot_ms` changes and
  ignores points outside [min, max]: a frame with nothing to report sends one point beyond
  `max_distance` (id 65535), which clears the old set and keeps the sensor healthy.
- DEBUG_VECT (250) "CUT": the target cut point in body FRD metres (NaN when there is none), for
  PX4 (which has no 3D obstacle message) and for flight logs.

The target branch goes into OBSTACLE_DISTANCE_3D only with `target_as_obstacle`. ArduPilot's
MAVLink proximity backend also files DISTANCE_SENSOR readings whose orientation is one of the
eight horizontal directions into its fence (AP_Proximity_MAV::handle_distance_sensor_msg), so
unless the target is meant to be an obstacle, DISTANCE_SENSOR carries orientation CUSTOM (100)
with the mount quaternion: rangefinder consumers and logs still read it, the fence does not.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from branchrange.config import MavlinkConfig
from branchrange.mavlink.frames import MAV_SENSOR_ROTATION_CUSTOM, CameraMount

#: obstacle_id of the out-of-range point that clears ArduPilot's obstacle set.
NO_OBSTACLE_ID = 65535
DEBUG_VECT_NAME = b"CUT"


def heartbeat(camera_lost: bool) -> mavlink2.MAVLink_heartbeat_message:
    """HEARTBEAT of an onboard computer: status CRITICAL while the camera is lost, else ACTIVE."""
    status = mavlink2.MAV_STATE_CRITICAL if camera_lost else mavlink2.MAV_STATE_ACTIVE
    return mavlink2.MAVLink_heartbeat_message(
        mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, status, 3)


def target_branch(result: Mapping[str, Any] | None) -> Mapping[str, Any] | None:
    """The branch `result["target_id"]` names, or None (no result, no target, unknown id)."""
    if result is None or result.get("target_id") is None:
        return None
    return next((b for b in result.get("branches", []) if b.get("id") == result["target_id"]), None)


def distance_sensor(target: Mapping[str, Any] | None, mount: CameraMount, cfg: MavlinkConfig,
                    time_boot_ms: int) -> mavlink2.MAVLink_distance_sensor_message:
    """DISTANCE_SENSOR for the target branch (camera → cut point, cm), or "nothing in range"."""
    max_cm = round(cfg.max_distance_m * 100)
    if target is None:
        current_cm = max_cm + 1
    else:
        current_cm = min(round(math.dist((0.0, 0.0, 0.0), target["cut_point_m"]) * 100), 65534)
    if cfg.target_as_obstacle:
        orientation = mount.sensor_orientation()
    else:
        orientation = MAV_SENSOR_ROTATION_CUSTOM
    quaternion = mount.quaternion_wxyz if orientation == MAV_SENSOR_ROTATION_CUSTOM else (0.0, 0.0, 0.0, 0.0)
    return mavlink2.MAVLink_distance_sensor_message(
        time_boot_ms, round(cfg.min_distance_m * 100), max_cm, current_cm,
        mavlink2.MAV_DISTANCE_SENSOR_UNKNOWN, cfg.sensor_id, orientation, 255,
        0.0, 0.0, quaternion, 0)


def obstacles_3d(result: Mapping[str, Any] | None, mount: CameraMount, cfg: MavlinkConfig,
                 time_boot_ms: int) -> list[mavlink2.MAVLink_obstacle_distance_3d_message]:
    """OBSTACLE_DISTANCE_3D for every cut point (target only with `target_as_obstacle`), body FRD."""
    branches = [] if result is None else list(result.get("branches", []))
    if not cfg.target_as_obstacle and result is not None:
        branches = [b for b in branches if b.get("id") != result.get("target_id")]

    def message(obstacle_id: int, xyz: Any) -> mavlink2.MAVLink_obstacle_distance_3d_message:
        return mavlink2.MAVLink_obstacle_distance_3d_message(
            time_boot_ms, mavlink2.MAV_DISTANCE_SENSOR_UNKNOWN, mavlink2.MAV_FRAME_BODY_FRD,
            obstacle_id, float(xyz[0]), float(xyz[1]), float(xyz[2]),
            cfg.min_distance_m, cfg.max_distance_m)

    if not branches:
        return [message(NO_OBSTACLE_ID, (cfg.max_distance_m + 1.0, 0.0, 0.0))]
    return [message(int(b["id"]) & 0xFFFF, mount.to_body(b["cut_point_m"])) for b in branches]


def debug_vect(target: Mapping[str, Any] | None, mount: CameraMount,
               time_boot_ms: int) -> mavlink2.MAVLink_debug_vect_message:
    """DEBUG_VECT "CUT": the target cut point in body FRD metres, NaN when there is no target."""
    xyz = (math.nan,) * 3 if target is None else mount.to_body(target["cut_point_m"])
    return mavlink2.MAVLink_debug_vect_message(
        DEBUG_VECT_NAME, time_boot_ms * 1000, float(xyz[0]), float(xyz[1]), float(xyz[2]))


def frame_messages(result: Mapping[str, Any] | None, mount: CameraMount, cfg: MavlinkConfig,
                   time_boot_ms: int) -> list[mavlink2.MAVLink_message]:
    """All messages of one frame (None = no target), sharing `time_boot_ms`, in sending order."""
    target = target_branch(result)
    return [distance_sensor(target, mount, cfg, time_boot_ms),
            *obstacles_3d(result, mount, cfg, time_boot_ms),
            debug_vect(target, mount, time_boot_ms)]
