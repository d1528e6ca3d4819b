"""A loopback autopilot for the tests: real MAVLink 2 over UDP on 127.0.0.1, flying a trajectory in real time.

`AutopilotSim` listens on `udpin:127.0.0.1:<free port>` (the relay connects with `udpout:`), and
from its own thread, at the wall-clock times they are due:
- sends HEARTBEAT every `heartbeat_period_s` as an ArduPilot copter (type QUADROTOR, autopilot
  ARDUPILOTMEGA, custom_mode 4 = GUIDED or 5 = LOITER, armed or not) — or as a GCS when told to;
- answers COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL with COMMAND_ACK and from then on streams that
  message (ATTITUDE, LOCAL_POSITION_NED) at the requested rate, stamped with its own time_boot_ms
  (it "booted" `boot_age_s` before the test started, so the relay must align clocks);
- answers PARAM_REQUEST_READ (by name or index) with PARAM_VALUE from its `params`: the parameters
  BranchRange needs, at the values it needs (`ARDUPILOT_PARAMS`, or `PX4_PARAMS` as PX4), overridden
  by the `params` given; a name it does not hold gets no answer, as on a real autopilot. As PX4
  (`autopilot=MAV_AUTOPILOT_PX4`) it sends integers bytewise in the float, as PX4 does;
- records every message it receives with its arrival time (`time.monotonic()`), or hands each to
  `listener` instead (a soak of an hour would hold hundreds of thousands of messages).
With `signing_key` it signs what it sends and rejects what is not signed with that key.
Faults of a real flight controller, for the soak (`benchmarks/soak.py`): `reboot()` (time_boot_ms
starts again at 0 and the requested streams are forgotten, as after a power cycle), `silence(s)`
(nothing sent for that long), `wrong_key(key, s)` (signs with another key for that long; what it
receives is still recorded), `flood(rate_hz, s)` (NAMED_VALUE_FLOAT nobody asked for at that rate).
The trajectory maps seconds since the simulator started to a `SimPose` (body FRD in local NED).

`fly_frames` plays the daemon's side: frames captured at a rate, each published to a relay a fixed
latency after capture with its capture time, holding the true cut points seen from the true camera
pose at capture plus the noise the tracker's measurement model assumes. The tests and
`benchmarks/pose_compensation.py` both use it.

`fly_daemon` runs the real daemon instead (`branchrange.onboard.daemon.Daemon`, its pipeline and a real
`MavlinkRelay`) on a `branchrange synth-flight` recording released at its timestamps (decoded into
memory first: `PreloadedReplay`), while the simulator flies the recording's camera poses;
`benchmarks/pose_compensation.py --flight` and `benchmarks/approach.py` use it.
"""

from __future__ import annotations

import dataclasses
import math
import struct
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mavlink_peer import Received
from result_factory import branch, frame_result

from branchrange.config.loader import Config
from branchrange.config.sections import TrackingConfig
from branchrange.core.frame_result import FrameResult, WorldTargets
from branchrange.offline.flight import FlightPose, FlightTruth
from branchrange.onboard.mavlink import MavlinkRelay
from branchrange.onboard.mavlink.connection import mavutil_v2
from branchrange.onboard.mavlink.frames import CameraMount, rotation_exp, rotation_from_rpy, rotation_log
from camera.sources import PreloadedReplay, ReplaySource

ARDUCOPTER_GUIDED, ARDUCOPTER_LOITER = 4, 5
MAV_TYPE_QUADROTOR, MAV_TYPE_GCS = 2, 6
MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_INVALID, MAV_AUTOPILOT_PX4 = 3, 8, 12
#: What a correctly set up autopilot holds (branchrange.onboard.preflight.autopilot_parameters).
ARDUPILOT_PARAMS: dict[str, float] = {"PRX1_TYPE": 2, "AVOID_ENABLE": 7, "AVOID_MARGIN": 1.0, "SYSID_THISMAV": 1}
PX4_PARAMS: dict[str, float] = {"CP_DIST": -1.0, "MAV_SYS_ID": 1, "MAV_1_MODE": 2}
MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32 = 6, 9
ATTITUDE_ID, LOCAL_POSITION_NED_ID = 30, 32


@dataclass(frozen=True)
class SimPose:
    """Body FRD in local NED: `rotation` (3×3 R_ned_body), `position_m` (3,)."""

    rotation: np.ndarray
    position_m: np.ndarray

    def ned_to_body(self, point_ned_m: np.ndarray) -> np.ndarray:
        """Body FRD metres of a NED point (3,)."""
        return self.rotation.T @ (np.asarray(point_ned_m, dtype=np.float64) - self.position_m)


Trajectory = Callable[[float], SimPose]


def approach_flight(
    speed_m_s: float,
    start_ned_m=(0.0, 0.0, -2.0),
    heading_deg: float = 20.0,
    sway_m: float = 0.05,
    yaw_swing_deg: float = 6.0,
    tilt_deg: float = 3.0,
) -> Trajectory:
    """A copter closing on a branch: straight at `speed_m_s` along `heading_deg`, swaying sideways
    (amplitude `sway_m`, 0.5 Hz), yawing ±`yaw_swing_deg` (0.3 Hz) and rolling/pitching ±`tilt_deg`."""
    start = np.asarray(start_ned_m, dtype=np.float64)
    h = math.radians(heading_deg)
    forward = np.array([math.cos(h), math.sin(h), 0.0])
    right = np.array([-math.sin(h), math.cos(h), 0.0])

    def pose(t: float) -> SimPose:
        position = start + forward * speed_m_s * t + right * sway_m * math.sin(2 * math.pi * 0.5 * t)
        roll = tilt_deg * math.sin(2 * math.pi * 0.5 * t)
        pitch = -tilt_deg * 0.5 * math.cos(2 * math.pi * 0.4 * t)
        yaw = heading_deg + yaw_swing_deg * math.sin(2 * math.pi * 0.3 * t)
        return SimPose(rotation_from_rpy(roll, pitch, yaw), position)

    return pose


def flight_from_camera_poses(
    poses: list[FlightPose], mount: CameraMount, start_ned_m=(0.0, 0.0, -2.0), heading_deg: float = 0.0
):
    """A camera flight (`FlightTruth.poses` of a `flight.json`, as `branchrange synth-flight` writes it:
    world = the camera frame of the first pose, `X_world = R_world_cam · X_cam + t_world_cam`) flown
    by a vehicle carrying the camera on `mount`, whose body is level at `start_ned_m` facing
    `heading_deg` at the first pose. Returns (trajectory, world_to_ned); the trajectory's time is
    seconds since the first pose, the body pose between poses is interpolated (position linearly,
    attitude along the shortest rotation) and held beyond the ends."""
    r_ned_body0 = rotation_from_rpy(0.0, 0.0, heading_deg)
    r_ned_world = r_ned_body0 @ mount.camera_to_body @ poses[0].R_world_cam.T
    origin = np.asarray(start_ned_m, dtype=np.float64) + r_ned_body0 @ mount.translation_m
    origin = origin - r_ned_world @ poses[0].t_world_cam

    def world_to_ned(point_world_m) -> np.ndarray:
        return r_ned_world @ np.asarray(point_world_m, dtype=np.float64) + origin

    bodies = []
    for pose in poses:
        r_ned_body = r_ned_world @ pose.R_world_cam @ mount.camera_to_body.T
        bodies.append(SimPose(r_ned_body, world_to_ned(pose.t_world_cam) - r_ned_body @ mount.translation_m))
    times = np.array([(pose.timestamp_ns - poses[0].timestamp_ns) / 1e9 for pose in poses])

    def pose(t: float) -> SimPose:
        i = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2))
        s = float(np.clip((t - times[i]) / (times[i + 1] - times[i]), 0.0, 1.0))
        a, b = bodies[i], bodies[i + 1]
        rotation = a.rotation @ rotation_exp(s * rotation_log(a.rotation.T @ b.rotation))
        return SimPose(rotation, a.position_m + s * (b.position_m - a.position_m))

    return pose, world_to_ned


def _rates(trajectory: Trajectory, t: float, dt: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """NED velocity (3,) m/s and body angular rates (3,) rad/s by central differences."""
    a, b = trajectory(t - dt), trajectory(t + dt)
    velocity = (b.position_m - a.position_m) / (2 * dt)
    body_rates = rotation_log(a.rotation.T @ b.rotation) / (2 * dt)
    return velocity, body_rates


class AutopilotSim:
    """See the module docstring. Use as a context manager; `port` is where it listens."""

    def __init__(
        self,
        trajectory: Trajectory,
        *,
        heartbeat_period_s: float = 1.0,
        mode: int = ARDUCOPTER_GUIDED,
        armed: bool = True,
        mav_type: int = MAV_TYPE_QUADROTOR,
        autopilot: int = MAV_AUTOPILOT_ARDUPILOTMEGA,
        signing_key: bytes | None = None,
        answer_interval_requests: bool = True,
        boot_age_s: float = 100.0,
        listener: Callable[[Received], None] | None = None,
        poll_s: float = 0.001,
        params: Mapping[str, float] | None = None,
    ):
        self.trajectory = trajectory
        self.heartbeat_period_s = heartbeat_period_s
        self.mode, self.armed, self.mav_type, self.autopilot = mode, armed, mav_type, autopilot
        self.answer_interval_requests = answer_interval_requests
        defaults = PX4_PARAMS if autopilot == MAV_AUTOPILOT_PX4 else ARDUPILOT_PARAMS
        self.params: dict[str, float] = {**defaults, **(params or {})}
        self.heartbeats_on = True
        self.heartbeats_sent = 0
        self.received: list[Received] = []
        self.listener = listener
        self.poll_s = poll_s  # how often its thread wakes (s): finer times in the tests, less CPU in a soak
        self.signing_key = signing_key
        self._silent_until = self._wrong_key_until = self._flood_until = 0.0
        self._flood_rate_hz = 0.0
        self._flood_sent = 0
        self._flood_start = 0.0
        self.rates_hz: dict[int, float] = {}
        self.mavlink = mavutil_v2().mavlink  # the dialect module: message ids and enums
        self.conn = mavutil_v2().mavlink_connection("udpin:127.0.0.1:0", source_system=1, source_component=1)
        if signing_key is not None:
            self.conn.setup_signing(signing_key, sign_outgoing=True, allow_unsigned_callback=None, link_id=0)
        self.start = time.monotonic()
        self.boot = self.start - boot_age_s  # the autopilot's time_boot_ms counts from here
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="autopilot-sim", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        return self.conn.port.getsockname()[1]

    def pose_at(self, t_monotonic: float) -> SimPose:
        """The true pose at a `time.monotonic()` instant."""
        return self.trajectory(t_monotonic - self.start)

    def of_type(self, name: str) -> list[Received]:
        with self._lock:
            return [r for r in self.received if r.type == name]

    def reboot(self) -> None:
        """A power cycle: time_boot_ms starts again at 0 and the streams asked for are forgotten."""
        with self._lock:
            self.boot = time.monotonic()
            self.rates_hz.clear()

    def silence(self, seconds: float) -> None:
        """Send nothing at all (heartbeats, streams, acks) for `seconds`."""
        self._silent_until = time.monotonic() + seconds

    def wrong_key(self, key: bytes, seconds: float) -> None:
        """Sign with `key` instead of the configured one for `seconds`; everything received is still recorded."""
        with self._lock:
            self.conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=lambda *_: True, link_id=0)
            self._wrong_key_until = time.monotonic() + seconds

    def flood(self, rate_hz: float, seconds: float) -> None:
        """Send NAMED_VALUE_FLOAT (unrelated to BranchRange) at `rate_hz` for `seconds`."""
        with self._lock:
            self._flood_start, self._flood_sent = time.monotonic(), 0
            self._flood_rate_hz, self._flood_until = rate_hz, self._flood_start + seconds

    def _end_faults(self, now: float) -> None:
        """Back to the configured key once a wrong-key spell is over."""
        if self._wrong_key_until and now >= self._wrong_key_until:
            self._wrong_key_until = 0.0
            if self.signing_key is not None:
                self.conn.setup_signing(self.signing_key, sign_outgoing=True, allow_unsigned_callback=None, link_id=0)
            else:  # unsigned again
                self.conn.mav.signing.secret_key, self.conn.mav.signing.sign_outgoing = None, False

    def _send_flood(self, now: float) -> None:
        due = int((min(now, self._flood_until) - self._flood_start) * self._flood_rate_hz)
        for _ in range(due - self._flood_sent):
            self.conn.mav.named_value_float_send(self._time_boot_ms(now), b"FLOOD", float(self._flood_sent))
            self._flood_sent += 1

    def _time_boot_ms(self, now: float) -> int:
        return max(0, int((now - self.boot) * 1000))  # a reboot from another thread may come after `now`

    def _heartbeat(self) -> None:
        m = self.mavlink
        base_mode = m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (m.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        self.conn.mav.heartbeat_send(self.mav_type, self.autopilot, base_mode, self.mode, 4 if self.armed else 3)
        self.heartbeats_sent += 1

    def _stream(self, message_id: int, now: float) -> None:
        pose = self.trajectory(now - self.start)
        velocity, rates = _rates(self.trajectory, now - self.start)
        boot_ms = self._time_boot_ms(now)
        if message_id == ATTITUDE_ID:
            r = pose.rotation  # Z-Y-X Euler angles of R_ned_body
            roll, pitch, yaw = math.atan2(r[2, 1], r[2, 2]), -math.asin(r[2, 0]), math.atan2(r[1, 0], r[0, 0])
            self.conn.mav.attitude_send(boot_ms, roll, pitch, yaw, *(float(w) for w in rates))
        else:
            self.conn.mav.local_position_ned_send(
                boot_ms, *(float(v) for v in pose.position_m), *(float(v) for v in velocity)
            )

    def _send_param(self, index: int) -> None:
        """PARAM_VALUE of the parameter at `index` of `params`: an int as INT32 (PX4: its bytes in the float)."""
        name, value = list(self.params.items())[index]
        kind = MAV_PARAM_TYPE_INT32 if isinstance(value, int) else MAV_PARAM_TYPE_REAL32
        if kind == MAV_PARAM_TYPE_INT32 and self.autopilot == MAV_AUTOPILOT_PX4:
            value = struct.unpack("<f", struct.pack("<i", value))[0]
        self.conn.mav.param_value_send(name.encode("ascii"), float(value), kind, len(self.params), index)

    def _answer_param_read(self, msg) -> None:
        names = list(self.params)
        index = names.index(msg.param_id) if msg.param_index < 0 and msg.param_id in names else msg.param_index
        if 0 <= index < len(names):
            self._send_param(index)

    def _handle(self, msg, now: float) -> None:
        if self.listener is not None:
            self.listener(Received(msg, now))
        else:
            with self._lock:
                self.received.append(Received(msg, now))
        if now < self._silent_until:
            return
        if msg.get_type() == "PARAM_REQUEST_READ":
            self._answer_param_read(msg)
        if msg.get_type() == "COMMAND_LONG" and msg.command == self.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            if not self.answer_interval_requests:
                return
            result = self.mavlink.MAV_RESULT_ACCEPTED
            if int(msg.param1) in (ATTITUDE_ID, LOCAL_POSITION_NED_ID) and msg.param2 > 0:
                self.rates_hz[int(msg.param1)] = 1e6 / msg.param2
            else:
                result = self.mavlink.MAV_RESULT_UNSUPPORTED
            self.conn.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def _run(self) -> None:
        next_beat = time.monotonic()
        next_stream: dict[int, float] = {}
        while not self._stop.is_set():
            now = time.monotonic()
            while (msg := self.conn.recv_msg()) is not None:
                if msg.get_type() != "BAD_DATA":
                    self._handle(msg, now)
            if not self.conn.clients or now < self._silent_until:  # nobody to send to yet, or told to be silent
                time.sleep(max(self.poll_s, 0.002))
                continue
            with self._lock:
                self._end_faults(now)
                if now < self._flood_until + 0.1:
                    self._send_flood(now)
            if self.heartbeats_on and now >= next_beat:
                self._heartbeat()
                next_beat = now + self.heartbeat_period_s
            for message_id, rate in list(self.rates_hz.items()):
                if now >= next_stream.get(message_id, 0.0):
                    self._stream(message_id, now)
                    next_stream[message_id] = max(next_stream.get(message_id, now) + 1.0 / rate, now)
            time.sleep(self.poll_s)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.conn.close()

    def __enter__(self) -> AutopilotSim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def camera_point(pose: SimPose, point_ned_m: np.ndarray, mount: CameraMount) -> np.ndarray:
    """Where the camera on `mount` sees a NED point (camera frame, metres, (3,))."""
    return mount.camera_to_body.T @ (pose.ned_to_body(point_ned_m) - mount.translation_m)


#: The camera the simulated results come from: a ZED Mini at HD720 (f ≈ 640 px, B = 63 mm).
SIM_FOCAL_PX, SIM_BASELINE_M = 640.0, 0.063


def noisy(point_cam_m: np.ndarray, rng: np.random.Generator, tracking: TrackingConfig) -> np.ndarray:
    """A cut point with the noise `tracking` assumes for the simulated camera (`TrackingConfig.sigmas_m`):
    depth σ = disparity_sigma_px·r² / (f·B), lateral σ = lateral_sigma_px·r / f."""
    r = float(np.linalg.norm(point_cam_m))
    u = point_cam_m / r
    lateral_sigma, depth_sigma = tracking.sigmas_m(r, SIM_FOCAL_PX, SIM_BASELINE_M)
    lateral = rng.normal(0.0, lateral_sigma, 3)
    lateral -= u * (lateral @ u)
    return point_cam_m + lateral + u * rng.normal(0.0, depth_sigma)


@dataclass(frozen=True)
class Published:
    """One frame handed to the relay: capture and publish times (monotonic s), the target's camera point (3,)."""

    captured_at: float
    published_at: float
    target_cam_m: np.ndarray


def fly_frames(
    sim: AutopilotSim,
    relay,
    mount: CameraMount,
    branches_ned: list[np.ndarray],
    frames: int,
    fps: float,
    latency_s: float,
    rng: np.random.Generator,
    tracking: TrackingConfig,
) -> list[Published]:
    """Capture `frames` frames at `fps` and publish each `latency_s` after capture (branch 0 is the target)."""
    t0 = time.monotonic() + 0.01
    published = []
    for k in range(frames):
        captured = t0 + k / fps
        time.sleep(max(0.0, captured + latency_s - time.monotonic()))
        pose = sim.pose_at(captured)
        cams = [noisy(camera_point(pose, p, mount), rng, tracking) for p in branches_ned]
        result = frame_result(
            [branch(i, c, confidence=0.8) for i, c in enumerate(cams)],
            target_id=0,
            focal_px=SIM_FOCAL_PX,
            baseline_m=SIM_BASELINE_M,
        )
        relay.publish(result, captured_at=captured)
        published.append(Published(captured, time.monotonic(), cams[0]))
    return published


def body_target_errors(
    sim: AutopilotSim, published: list[Published], mount: CameraMount, target_ned: np.ndarray, skip_frames: int
) -> tuple[list[float], list[float]]:
    """Per DEBUG_VECT the sim received after `skip_frames` publications: the error (m) of the sent target and
    of the uncompensated one (the newest result through the mount alone) against the truth in the body
    frame at the moment it arrived."""
    compensated, uncompensated = [], []
    for r in sim.of_type("DEBUG_VECT"):
        newest = [p for p in published if p.published_at <= r.at]
        if len(newest) <= skip_frames or math.isnan(r.msg.x):
            continue
        truth = sim.pose_at(r.at).ned_to_body(target_ned)
        compensated.append(float(np.linalg.norm(np.array([r.msg.x, r.msg.y, r.msg.z]) - truth)))
        uncompensated.append(float(np.linalg.norm(mount.to_body(newest[-1].target_cam_m) - truth)))
    return compensated, uncompensated


def flight_clock(sim: AutopilotSim) -> Callable[[], int]:
    """A replay clock (monotonic ns) that starts the simulator's flight when the replay first reads it,
    which is when it releases the first frame (`ReplaySource` paces the rest from there)."""
    started = False

    def clock() -> int:
        nonlocal started
        now = time.monotonic_ns()
        if not started:
            sim.start, started = now / 1e9, True  # flight time 0 = the first pose, released now
        return now

    return clock


class TimedRelay(MavlinkRelay):
    """A `MavlinkRelay` that notes, per frame index, when the daemon captured and published each result
    (monotonic s): the start of the capture → send latency the benchmarks measure at the autopilot."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.publications: dict[int, tuple[float, float]] = {}  # frame index → (captured_at, published_at)

    def publish(self, result: FrameResult, captured_at: float | None = None) -> None:
        """Note the times, then hand over as the relay does."""
        published_at = time.monotonic()
        self.publications[result.frame.index] = (published_at if captured_at is None else captured_at, published_at)
        super().publish(result, captured_at)


@dataclass
class DaemonFlight:
    """What a daemon replay against the simulator left behind.

    `sim` (closed; `received` holds every message the autopilot got, with arrival times), `published`
    (monotonic s when the daemon's observers saw it, the result as logged, with its fused `targets`),
    `publications` (frame index → captured_at, published_at, monotonic s), the flight's `truth`, its
    `world_to_ned` map, the relay's `final_targets`, and the daemon's frame counters."""

    sim: AutopilotSim
    published: list[tuple[float, FrameResult]]
    publications: dict[int, tuple[float, float]]
    truth: FlightTruth
    world_to_ned: Callable[[np.ndarray], np.ndarray]
    final_targets: WorldTargets
    counters: dict[str, int]

    def cuts_ned(self) -> dict[int, np.ndarray]:
        """True cut point id → its local NED position (3,) m."""
        return {c.id: self.world_to_ned(c.world_m) for c in self.truth.cut_points}


def fly_daemon(
    directory: Path,
    cfg: Config,
    mount: CameraMount,
    *,
    start_ned_m=(0.0, 0.0, -2.0),
    heading_deg: float = 0.0,
    ignore_masks: bool = False,
) -> DaemonFlight:
    """Replay `directory` through the daemon (config `cfg`, its `mavlink.url` pointed at the simulator) while
    the simulator (GUIDED, armed) flies its flight.json, hovering at the first pose until the first frame
    is released. `ignore_masks` leaves the recording's masks unread (the built-in segmenter finds the
    branches, as for a live camera). The pipeline is warmed
    up on the first frame before the clock starts, so lazily built parts do not count as latency."""
    from branchrange.onboard.daemon import Daemon, relay_for

    truth = FlightTruth.load(directory)
    trajectory, world_to_ned = flight_from_camera_poses(truth.poses, mount, start_ned_m, heading_deg)
    published: list[tuple[float, FrameResult]] = []
    with AutopilotSim(trajectory, heartbeat_period_s=0.2) as sim:
        sim.start = time.monotonic() + 3600.0  # hover at the first pose until the first frame
        cfg = dataclasses.replace(cfg, mavlink=dataclasses.replace(cfg.mavlink, url=f"udpout:127.0.0.1:{sim.port}"))
        pipeline = _warm_pipeline(directory, cfg, ignore_masks)
        relay = relay_for(cfg, mount, TimedRelay)
        deadline = time.monotonic() + 5.0
        while not relay.link_state()["vehicle_state"]["available"] and time.monotonic() < deadline:
            time.sleep(0.02)
        replay = PreloadedReplay(directory, pace="recorded", clock=flight_clock(sim), ignore_masks=ignore_masks)
        daemon = Daemon(
            cfg,
            open_source=lambda: replay,
            pipeline=pipeline,
            relay=relay,
            results_path=cfg.log.results_jsonl or None,
            observers=[lambda result, _: published.append((time.monotonic(), result))],
        )
        try:
            daemon.run()
            time.sleep(0.2)  # the last sends arrive
            final = relay.targets()
        finally:
            daemon.close()
    counters = {"frames": daemon.frames, "dropped": daemon.dropped, "skipped": daemon.skipped, "late": daemon.late}
    return DaemonFlight(sim, published, relay.publications, truth, world_to_ned, final, counters)


def _warm_pipeline(directory: Path, cfg: Config, ignore_masks: bool) -> Any:
    """The daemon's pipeline for `cfg`, run once on the recording's first frame and reset."""
    from branchrange.config.loader import pipeline_for

    probe = ReplaySource(directory, pace="fast", ignore_masks=ignore_masks)
    try:
        pipeline = pipeline_for(cfg, probe.calibration)
        warm = next(probe)
        pipeline.process(warm.left, warm.right, mask=warm.mask)
        pipeline.reset()
    finally:
        probe.close()
    return pipeline
