"""The autopilot parameters BranchRange needs, per autopilot: one table each, as data.

Each `ParameterRule` names a parameter, what value it must have (`accepts`), the value to set
(`wanted`, as the operator types it into a ground station) and why. The values come from the onboard
guide (docs/onboard.md, "ArduPilot parameters" and "PX4 parameters") and the MAVLink reference:
BranchRange sends OBSTACLE_DISTANCE_3D and DISTANCE_SENSOR for the other branches and
DISTANCE_SENSOR + DEBUG_VECT `CUT` for the target.

ArduPilot Copter ≥ 4.3 (`PRX1_TYPE` was `PRX_TYPE` before):
- `PRX1_TYPE` = 2: the MAVLink proximity backend, which reads OBSTACLE_DISTANCE_3D into the fence;
- `AVOID_ENABLE` with bit 1 (2, "UseProximitySensor") set, 7 (fence, proximity, beacons) as documented;
- `AVOID_MARGIN` above 0 and below `mavlink.max_distance_m`: a margin beyond the farthest obstacle
  BranchRange reports would never hold the drone;
- `SYSID_THISMAV` = `mavlink.system_id`: BranchRange sends as the vehicle's system;
- with `mavlink.setpoint_enabled`: `WPNAV_SPEED` (cm/s) at most `mavlink.setpoint_max_speed_m_s`.

PX4 ≥ 1.14:
- `CP_DIST` < 0 (collision prevention off) while the target is not sent as an obstacle
  (`mavlink.target_as_obstacle = false`, for cutting): PX4 reads every DISTANCE_SENSOR not facing up or
  down, so with it on the drone stops `CP_DIST` short of the branch it has to cut; ≥ 0 with
  `target_as_obstacle = true` (inspection), as then the obstacles are meant to be kept away from;
- `MAV_SYS_ID` = `mavlink.system_id`;
- `MAV_1_MODE` = 2 (Onboard) on the companion's MAVLink instance (TELEM 2, as documented).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from branchrange.config.sections import MavlinkConfig

#: HEARTBEAT `autopilot` values (MAV_AUTOPILOT) BranchRange has parameter tables for.
MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4 = 3, 12
AUTOPILOT_NAMES = {MAV_AUTOPILOT_ARDUPILOTMEGA: "ArduPilot", MAV_AUTOPILOT_PX4: "PX4"}
#: MAVLink instance mode "Onboard" of PX4's `MAV_n_MODE`.
PX4_MAV_MODE_ONBOARD = 2
#: ArduPilot's `AVOID_ENABLE` bit for proximity sensors (bit 1, "UseProximitySensor").
AVOID_USE_PROXIMITY = 2


@dataclass(frozen=True)
class ParameterRule:
    """One parameter the autopilot must hold: `accepts(value)`; `wanted` is the value to set, `why` the reason."""

    name: str
    wanted: str
    why: str
    accepts: Callable[[float], bool]


def _equals(expected: float) -> Callable[[float], bool]:
    return lambda value: value == expected


def _at_least(minimum: float) -> Callable[[float], bool]:
    return lambda value: value >= minimum


def ardupilot_rules(mavlink: MavlinkConfig) -> tuple[ParameterRule, ...]:
    """ArduPilot Copter's table (see the module docstring) for the `[mavlink]` settings in use."""
    max_range = mavlink.max_distance_m
    rules = [
        ParameterRule("PRX1_TYPE", "2", "the MAVLink proximity backend reads OBSTACLE_DISTANCE_3D", _equals(2)),
        ParameterRule(
            "AVOID_ENABLE",
            "7",
            "bit 1 (2) makes avoidance use proximity obstacles",
            lambda value: (int(value) & AVOID_USE_PROXIMITY) != 0,
        ),
        ParameterRule(
            "AVOID_MARGIN",
            "1.0",
            f"metres kept from obstacles: above 0 and below mavlink.max_distance_m ({max_range:g} m)",
            lambda value: 0 < value < max_range,
        ),
        ParameterRule(
            "SYSID_THISMAV",
            str(mavlink.system_id),
            "BranchRange sends as the vehicle's system (mavlink.system_id)",
            _equals(mavlink.system_id),
        ),
    ]
    if mavlink.setpoint_enabled:
        top_speed_cm_s = round(mavlink.setpoint_max_speed_m_s * 100)
        rules.append(
            ParameterRule(
                "WPNAV_SPEED",
                str(top_speed_cm_s),
                "GUIDED approach speed (cm/s) at most mavlink.setpoint_max_speed_m_s",
                lambda value: value <= top_speed_cm_s,
            )
        )
    return tuple(rules)


def px4_rules(mavlink: MavlinkConfig) -> tuple[ParameterRule, ...]:
    """PX4's table (see the module docstring) for the `[mavlink]` settings in use."""
    if mavlink.target_as_obstacle:
        collision = ParameterRule(
            "CP_DIST", "1.0", "the target is sent as an obstacle: collision prevention keeps clear of it", _at_least(0)
        )
    else:
        collision = ParameterRule(
            "CP_DIST",
            "-1",
            "collision prevention would stop the drone CP_DIST short of the branch to cut",
            lambda value: value < 0,
        )
    return (
        collision,
        ParameterRule(
            "MAV_SYS_ID",
            str(mavlink.system_id),
            "BranchRange sends as the vehicle's system (mavlink.system_id)",
            _equals(mavlink.system_id),
        ),
        ParameterRule(
            "MAV_1_MODE",
            str(PX4_MAV_MODE_ONBOARD),
            "the companion's MAVLink instance in Onboard mode",
            _equals(PX4_MAV_MODE_ONBOARD),
        ),
    )


def rules_for(autopilot: int, mavlink: MavlinkConfig) -> tuple[ParameterRule, ...] | None:
    """The table of the HEARTBEAT's `autopilot` (MAV_AUTOPILOT); None for an autopilot BranchRange has none for."""
    if autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return ardupilot_rules(mavlink)
    if autopilot == MAV_AUTOPILOT_PX4:
        return px4_rules(mavlink)
    return None
