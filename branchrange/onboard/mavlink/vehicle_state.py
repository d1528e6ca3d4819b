"""The vehicle's pose from the autopilot, on the companion's clock, at any recent instant.

The autopilot streams ATTITUDE (roll/pitch/yaw of body FRD in local NED, body rates) and
LOCAL_POSITION_NED (position and velocity in local NED), each stamped with its own
`time_boot_ms`. A frame's cut points need the pose at the frame's capture time, which the
daemon gives on the companion's `time.monotonic()` clock.

Clock alignment — receive time with a measured offset (not TIMESYNC): every state message gives
`received_at − time_boot` = clock offset + transport delay. The delay is never negative, so the
smallest value over the last `OFFSET_WINDOW_S` seconds is the offset plus the *smallest* delay
(on a 921600-baud UART ~0.5 ms for these 28–36-byte messages, on loopback UDP well below 1 ms,
plus the link thread's polling period at worst when every message waited for a poll, which the
minimum filters out as soon as one arrives just before a poll). The window lets the estimate follow
the few ppm the two crystals drift apart, and a `time_boot` that jumps back (autopilot reboot)
starts it afresh. TIMESYNC would need the autopilot to answer our requests (ArduPilot does, PX4
does, many bridges and simulators do not); the minimum-delay offset needs only the stream we
already asked for, and its error (the smallest delay, ~1 ms) moves a target by 0.5 mm at 0.5 m/s.

Interpolation: position linearly between the bracketing LOCAL_POSITION_NED samples, attitude along
the shortest rotation between the bracketing ATTITUDE samples; past the newest sample the pose is
extrapolated with the reported velocity and body rates, for at most `max_extrapolation_s`.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np

from branchrange.onboard.mavlink.frames import rotation_exp, rotation_from_rpy, rotation_log

#: Seconds of samples the minimum-delay clock offset looks back over.
OFFSET_WINDOW_S = 10.0
#: A time_boot this far behind the newest one means the autopilot rebooted.
REBOOT_JUMP_S = 1.0
#: Seconds of pose history kept: frames later than this after capture have no pose.
HISTORY_S = 5.0


@dataclass(frozen=True)
class Pose:
    """Body FRD → local NED at companion time `t` (s): `rotation` (3×3, R_ned_body), `position_m` (3,)."""

    t: float
    rotation: np.ndarray
    position_m: np.ndarray

    def body_to_ned(self, points_body_m: np.ndarray) -> np.ndarray:
        """Local NED metres of body FRD points, shape (3,) or (N, 3)."""
        return np.asarray(points_body_m, dtype=np.float64) @ self.rotation.T + self.position_m

    def ned_to_body(self, points_ned_m: np.ndarray) -> np.ndarray:
        """Body FRD metres of local NED points, shape (3,) or (N, 3)."""
        return (np.asarray(points_ned_m, dtype=np.float64) - self.position_m) @ self.rotation


class ClockOffset:
    """Autopilot `time_boot` seconds → companion monotonic seconds, by the minimum observed delay."""

    def __init__(self, window_s: float = OFFSET_WINDOW_S):
        self._window_s = window_s
        self._samples: deque[tuple[float, float]] = deque()  # (received_at, received_at − boot_s)
        self._newest_boot_s = -math.inf

    def observe(self, boot_s: float, received_at: float) -> None:
        """Note one message stamped `boot_s` (autopilot clock) that arrived at `received_at` (ours)."""
        if boot_s < self._newest_boot_s - REBOOT_JUMP_S:
            self._samples.clear()
        self._newest_boot_s = boot_s if not self._samples else max(self._newest_boot_s, boot_s)
        self._samples.append((received_at, received_at - boot_s))
        while self._samples[0][0] < received_at - self._window_s:
            self._samples.popleft()

    @property
    def offset_s(self) -> float | None:
        """Companion time minus autopilot time (s), None before the first message."""
        return min(d for _, d in self._samples) if self._samples else None

    def to_local(self, boot_s: float) -> float:
        """Companion monotonic time of autopilot time `boot_s`; call after at least one `observe`."""
        offset = self.offset_s
        if offset is None:
            raise RuntimeError("no autopilot time has been observed yet")
        return boot_s + offset


@dataclass(frozen=True)
class _PositionSample:
    position_m: np.ndarray  # (3,) NED
    velocity_m_s: np.ndarray  # (3,) NED


@dataclass(frozen=True)
class _AttitudeSample:
    rotation: np.ndarray  # (3, 3) R_ned_body
    rates_rad_s: np.ndarray  # (3,) body roll/pitch/yaw rates


S = TypeVar("S")


class _History(Generic[S]):
    """Samples sorted by companion time, the last `HISTORY_S` seconds; finds the pair around a time."""

    def __init__(self) -> None:
        self.times: list[float] = []
        self.samples: list[S] = []

    def add(self, t: float, sample: S) -> None:
        """Insert a sample at time `t` (s) and drop those older than the history length."""
        i = bisect.bisect_right(self.times, t)
        self.times.insert(i, t)
        self.samples.insert(i, sample)
        cut = bisect.bisect_left(self.times, self.times[-1] - HISTORY_S)
        del self.times[:cut], self.samples[:cut]

    def around(self, t: float) -> tuple[int, int] | None:
        """Indices (i, i+1) bracketing `t`, (last, last) past the newest sample, None before the oldest."""
        if not self.times or t < self.times[0]:
            return None
        i = bisect.bisect_right(self.times, t)
        if i >= len(self.times):
            return len(self.times) - 1, len(self.times) - 1
        return i - 1, i


class VehicleState:
    """Attitude and position history of one autopilot, queried at companion times.

    `handle(msg, received_at)` takes ATTITUDE and LOCAL_POSITION_NED (other types are ignored);
    `pose_at(t)` interpolates between samples, or extrapolates past the newest one (`pose_at(now)`).
    """

    def __init__(self, max_extrapolation_s: float = 0.5):
        self.max_extrapolation_s = max_extrapolation_s
        self.clock = ClockOffset()
        self._positions: _History[_PositionSample] = _History()
        self._attitudes: _History[_AttitudeSample] = _History()
        self.messages = 0

    def handle(self, msg: Any, received_at: float) -> bool:
        """Take one autopilot message; True when it was vehicle state."""
        kind = msg.get_type()
        if kind not in ("ATTITUDE", "LOCAL_POSITION_NED"):
            return False
        boot_s = msg.time_boot_ms / 1000.0
        self.clock.observe(boot_s, received_at)
        t = self.clock.to_local(boot_s)
        if kind == "ATTITUDE":
            rotation = rotation_from_rpy(math.degrees(msg.roll), math.degrees(msg.pitch), math.degrees(msg.yaw))
            self._attitudes.add(t, _AttitudeSample(rotation, np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed])))
        else:
            self._positions.add(t, _PositionSample(np.array([msg.x, msg.y, msg.z]), np.array([msg.vx, msg.vy, msg.vz])))
        self.messages += 1
        return True

    @property
    def has_state(self) -> bool:
        """Whether both attitude and position have been received."""
        return bool(self._positions.times and self._attitudes.times)

    @property
    def newest_sample_time(self) -> float | None:
        """Companion time (s) up to which both attitude and position are known, None without state."""
        if not self.has_state:
            return None
        return min(self._positions.times[-1], self._attitudes.times[-1])

    def _position_at(self, t: float) -> np.ndarray | None:
        pair = self._positions.around(t)
        if pair is None:
            return None
        i, j = pair
        a, ta = self._positions.samples[i], self._positions.times[i]
        if i == j:
            if t - ta > self.max_extrapolation_s:
                return None
            return a.position_m + a.velocity_m_s * (t - ta)
        b, tb = self._positions.samples[j], self._positions.times[j]
        s = 0.0 if tb <= ta else (t - ta) / (tb - ta)
        return a.position_m + s * (b.position_m - a.position_m)

    def _rotation_at(self, t: float) -> np.ndarray | None:
        pair = self._attitudes.around(t)
        if pair is None:
            return None
        i, j = pair
        a, ta = self._attitudes.samples[i], self._attitudes.times[i]
        if i == j:
            if t - ta > self.max_extrapolation_s:
                return None
            return a.rotation @ rotation_exp(a.rates_rad_s * (t - ta))  # body rates turn the body frame
        b, tb = self._attitudes.samples[j], self._attitudes.times[j]
        s = 0.0 if tb <= ta else (t - ta) / (tb - ta)
        return a.rotation @ rotation_exp(s * rotation_log(a.rotation.T @ b.rotation))

    def pose_at(self, t: float) -> Pose | None:
        """The pose at companion time `t` (s); None before the history or too far past its end."""
        rotation, position = self._rotation_at(t), self._position_at(t)
        if rotation is None or position is None:
            return None
        return Pose(t, rotation, position)

    def state(self, now: float) -> dict[str, Any]:
        """Facts for /health: whether a pose is available now, its age, the clock offset."""
        newest = self.newest_sample_time
        offset = self.clock.offset_s
        return {
            "available": self.pose_at(now) is not None,
            "messages": self.messages,
            "pose_age_s": None if newest is None else round(now - newest, 3),
            "clock_offset_s": None if offset is None else round(offset, 4),
        }
