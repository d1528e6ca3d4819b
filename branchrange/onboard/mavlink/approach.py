"""The optional approach setpoint: a standoff point before the target cut point, in local NED.

Off unless `mavlink.setpoint_enabled`. Sent (SET_POSITION_TARGET_LOCAL_NED, frame LOCAL_NED,
position + yaw) only while all of these hold, and not once any of them fails:
- the autopilot's HEARTBEAT arrived within the timeout, says armed, and its mode is one that
  follows external setpoints: ArduPilot GUIDED (custom_mode 4 on a copter) or PX4 OFFBOARD (main
  mode 6 in bits 16–23 of custom_mode);
- the vehicle pose is known now;
- there is a target track (it passed `world_tracks`' target rule: fresh within `mavlink.max_result_age_s`,
  consistent, confident), with at least `setpoint_min_observations` cut points and a recency-weighted
  confidence ≥ `setpoint_min_confidence`.
The point lies `setpoint_standoff_m` before the cut point along the horizontal line from the
vehicle to it, at the cut point's height, facing it; it is at most `setpoint_max_step_m` from the
vehicle and moves at most `setpoint_max_speed_m_s` × the time since the previous setpoint.

Autopilot side. ArduPilot: GUIDED mode, `GUID_OPTIONS` 0, `WPNAV_SPEED` (cm/s) at or below the
speed here; when setpoints stop the vehicle holds the last one (which is never beyond the standoff
and never more than `setpoint_max_step_m` ahead). PX4: OFFBOARD needs setpoints at ≥ 2 Hz before
and while in the mode (`send_rate_hz` ≥ 2 guarantees it); when they stop, `COM_OF_LOSS_T` (s)
later `COM_OBL_RC_ACT` (e.g. Hold) takes over; `MPC_XY_VEL_MAX` caps the speed.
"""

from __future__ import annotations

import math

import numpy as np

from branchrange.config.sections import MavlinkConfig
from branchrange.onboard.mavlink.connection import PeerHeartbeat
from branchrange.onboard.mavlink.vehicle_state import Pose
from branchrange.onboard.mavlink.world_tracks import Track

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
ARDUCOPTER_GUIDED = 4
PX4_MAIN_MODE_OFFBOARD = 6


def follows_setpoints(peer: PeerHeartbeat | None) -> bool:
    """Whether the autopilot is armed and in its external-setpoint mode (GUIDED / OFFBOARD)."""
    if peer is None or not peer.armed:
        return False
    if peer.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return peer.custom_mode == ARDUCOPTER_GUIDED
    if peer.autopilot == MAV_AUTOPILOT_PX4:
        return (peer.custom_mode >> 16) & 0xFF == PX4_MAIN_MODE_OFFBOARD
    return False


class ApproachPlanner:
    """Computes the next standoff setpoint, or None when one must not be sent."""

    def __init__(self, cfg: MavlinkConfig):
        self.cfg = cfg
        self._last: tuple[np.ndarray, float] | None = None  # previous setpoint (3,) NED and its time

    def reset(self) -> None:
        """Forget the previous setpoint: the next one is limited by `setpoint_max_step_m` only."""
        self._last = None

    def _target_ready(self, target: Track | None) -> bool:
        return (
            target is not None
            and target.observations >= self.cfg.setpoint_min_observations
            and target.confidence >= self.cfg.setpoint_min_confidence
        )

    def setpoint(
        self, target: Track | None, pose: Pose | None, peer: PeerHeartbeat | None, now: float
    ) -> tuple[np.ndarray, float] | None:
        """(setpoint (3,) NED m, yaw rad) for this send, or None (and the rate limit restarts)."""
        if not (
            self.cfg.setpoint_enabled and pose is not None and follows_setpoints(peer) and self._target_ready(target)
        ):
            self.reset()
            return None
        to_target = target.position_m - pose.position_m
        horizontal = np.array([to_target[0], to_target[1], 0.0])
        if np.linalg.norm(horizontal) < 1e-3:  # straight above or below: approach along the heading
            horizontal = pose.rotation[:, 0] * np.array([1.0, 1.0, 0.0])
        direction = horizontal / max(float(np.linalg.norm(horizontal)), 1e-9)
        goal = target.position_m - self.cfg.setpoint_standoff_m * direction
        goal = _limit_step(pose.position_m, goal, self.cfg.setpoint_max_step_m)
        if self._last is not None:
            previous, t_previous = self._last
            goal = _limit_step(previous, goal, self.cfg.setpoint_max_speed_m_s * max(now - t_previous, 0.0))
        self._last = (goal, now)
        return goal, math.atan2(direction[1], direction[0])


def _limit_step(start: np.ndarray, goal: np.ndarray, max_step_m: float) -> np.ndarray:
    """`goal` moved toward `start` so that it is at most `max_step_m` from it (metres, (3,))."""
    step = goal - start
    length = float(np.linalg.norm(step))
    return goal if length <= max_step_m else start + step * (max_step_m / length)
