"""The application's sections of the configuration file: where frames come from, the MAVLink link and the
world-frame target tracks, the HTTP service, the logs and load shedding.

The per-frame sections belong to the modules that use them (`[stereo]` `branchrange.core.pipeline.StereoConfig`,
`[roi]` `branchrange.core.roi.RoiConfig`, `[cutpoints]`, `[branch_tracking]`, `[masks]`, `[segmenter]`); these
are read by the daemon, the relay and the service above the per-frame core, so they live here, beside the loader
that gathers every section (`branchrange.config.loader.Config`).
"""

from __future__ import annotations

from dataclasses import dataclass

from branchrange.core.settings_check import Checks, ConfigError, Limit, Settings, in_physical_range

#: `log.level`: the logging levels the daemon and the service accept.
LOG_LEVELS: tuple[str, ...] = ("DEBUG", "INFO", "WARNING", "ERROR")


Vector3 = tuple[float, float, float]


@dataclass(frozen=True)
class CameraConfig(Settings):
    """Where frames come from and how the camera sits on the vehicle.

    `source` is a `camera.sources.open_source` spec; a ZED's mode is part of it
    (`zed:/dev/zedmini:HD720`, HD720 when left out). `calibration` is a calibration file that
    overrides what the source knows (a ZED factory `.conf` is read at the spec's mode).
    `mount_rpy_deg` is the camera's roll, pitch, yaw in degrees relative to a camera looking
    straight ahead (body FRD, right-handed: pitch > 0 tilts the optical axis up, yaw > 0 turns it
    right); `mount_xyz_m` the camera's optical centre in body FRD metres from the vehicle origin.
    `stall_timeout_s`: no frame for this long means the camera is lost (watchdog).
    """

    section = "camera"
    error = ConfigError
    limits = {"stall_timeout_s": Limit(exclusive_minimum=0, expected="seconds > 0")}

    source: str = "zed:0"
    calibration: str = ""
    mount_rpy_deg: Vector3 = (0.0, 0.0, 0.0)
    mount_xyz_m: Vector3 = (0.0, 0.0, 0.0)
    stall_timeout_s: float = 2.0

    def checks(self) -> Checks:
        """The rules beyond each key's `Limit`."""
        return {
            "source": (bool(self.source.strip()), "a source spec such as 'zed:0', 'oak' or 'replay:PATH'"),
        }


@dataclass(frozen=True)
class MavlinkConfig(Settings):
    """The link to the flight controller and what is sent over it (see `branchrange.onboard.mavlink`).

    `url` is a pymavlink connection string: `udpout:HOST:PORT`, `udpin:HOST:PORT`,
    `tcp:HOST:PORT`, or a serial device path with `baud`. `signing_key_file` holds the 32-byte
    MAVLink 2 signing key ("" = unsigned). `target_as_obstacle` sends the target branch to the
    autopilot's proximity fence too (off by default: ArduPilot keeps AVOID_MARGIN from every
    obstacle, so the drone would stop short of the branch it must cut). Results older than
    `max_result_age_s` are reported as "no target"; messages go out at least `send_rate_hz` times
    a second even without new results (ArduPilot and PX4 call a proximity sensor stale at 0.5 s).
    `enabled`: the daemon runs the relay (false: no MAVLink at all). `system_id`: the system id
    BranchRange sends as, the vehicle's SYSID_THISMAV. `component_id`: its component id
    (191 = MAV_COMP_ID_ONBOARD_COMPUTER). `min_distance_m`: the nearest distance DISTANCE_SENSOR and the
    obstacle messages say they measure (their min_distance). `max_distance_m`: the farthest (no target
    is sent as this + 1 cm, "nothing in range"). `sensor_id`: DISTANCE_SENSOR's sensor id.
    `reconnect_interval_s`: after a failed open or a send or read error the link is opened afresh this often.

    Vehicle state and link health (`branchrange.onboard.mavlink.vehicle_state`): the autopilot is asked for
    ATTITUDE and LOCAL_POSITION_NED at `state_rate_hz` (MAV_CMD_SET_MESSAGE_INTERVAL) unless
    `request_vehicle_state` is off; the link counts as connected only while the autopilot's
    HEARTBEAT arrives, lost after `heartbeat_timeout_s`; a pose older than `pose_timeout_s` is not
    used (targets then go out in the camera frame of their capture, as without vehicle state).
    `obstacle_min_confidence`: cut points below it are not sent as obstacles. 0.18: with the default
    learned segmenter and SGBM, the highest (calibrated) confidence, in hundredths, that keeps ≥ 98 % of
    the correct cut points (its calibration scenes in normal light) — a real branch must not vanish from the
    obstacle map.
    The approach setpoint (SET_POSITION_TARGET_LOCAL_NED, `branchrange.onboard.mavlink.approach`) is off
    unless `setpoint_enabled`: `setpoint_standoff_m` before the cut point, at most
    `setpoint_max_step_m` from the vehicle, moving at most `setpoint_max_speed_m_s`, only for a
    fresh target track with `setpoint_min_observations` and confidence ≥ `setpoint_min_confidence`.
    """

    section = "mavlink"
    error = ConfigError
    limits = {
        "baud": Limit(exclusive_minimum=0, expected="a positive baud rate"),
        "system_id": Limit(minimum=1, maximum=255, expected="an integer in [1, 255]"),
        "component_id": Limit(minimum=1, maximum=255, expected="an integer in [1, 255]"),
        "max_result_age_s": Limit(exclusive_minimum=0, expected="seconds > 0"),
        "send_rate_hz": Limit(minimum=2.0, expected="at least 2 Hz (autopilots call a sensor stale after 0.5 s)"),
        "min_distance_m": Limit.physical("distance_m"),
        "max_distance_m": Limit.physical("distance_m"),
        "sensor_id": Limit(minimum=0, maximum=255, expected="an integer in [0, 255]"),
        "reconnect_interval_s": Limit(exclusive_minimum=0, expected="seconds > 0"),
        "state_rate_hz": Limit(minimum=1.0, maximum=100.0, expected="a rate in [1, 100] Hz"),
        "heartbeat_timeout_s": Limit(exclusive_minimum=0, expected="seconds > 0 (MAVLink's usual is 3)"),
        "pose_timeout_s": Limit(exclusive_minimum=0, maximum=5.0, expected="seconds in (0, 5]"),
        "obstacle_min_confidence": Limit(minimum=0.0, maximum=1.0, expected="a number in [0, 1]"),
        "setpoint_standoff_m": Limit(minimum=0, expected="metres >= 0"),
        "setpoint_max_step_m": Limit(exclusive_minimum=0, expected="metres > 0"),
        "setpoint_max_speed_m_s": Limit(exclusive_minimum=0, maximum=5.0, expected="a speed in (0, 5] m/s"),
        "setpoint_min_observations": Limit(minimum=1, expected="an integer >= 1"),
        "setpoint_min_confidence": Limit(minimum=0.0, maximum=1.0, expected="a number in [0, 1]"),
    }

    enabled: bool = True
    url: str = "udpout:127.0.0.1:14550"
    baud: int = 921600
    system_id: int = 1
    component_id: int = 191
    signing_key_file: str = ""
    target_as_obstacle: bool = False
    max_result_age_s: float = 0.5
    send_rate_hz: float = 4.0
    min_distance_m: float = 0.2
    max_distance_m: float = 10.0
    sensor_id: int = 0
    reconnect_interval_s: float = 1.0
    request_vehicle_state: bool = True
    state_rate_hz: float = 30.0
    heartbeat_timeout_s: float = 3.0
    pose_timeout_s: float = 0.5
    obstacle_min_confidence: float = 0.18
    setpoint_enabled: bool = False
    setpoint_standoff_m: float = 0.6
    setpoint_max_step_m: float = 1.0
    setpoint_max_speed_m_s: float = 0.5
    setpoint_min_observations: int = 5
    setpoint_min_confidence: float = 0.5

    def checks(self) -> Checks:
        """The range of every setting; the reported depth band within the physical distance range."""
        near_ok, _ = in_physical_range("distance_m", self.min_distance_m)
        far_ok, distances = in_physical_range("distance_m", self.max_distance_m)
        return {
            "url": (
                bool(self.url.strip()),
                "a pymavlink connection string such as 'udpout:127.0.0.1:14550' or '/dev/ttyTHS1'",
            ),
            "max_distance_m": (far_ok, distances),
            "min_distance_m": (
                near_ok and self.min_distance_m < self.max_distance_m,
                f"metres >= 0 and below mavlink.max_distance_m ({self.max_distance_m})",
            ),
        }


@dataclass(frozen=True)
class TrackingConfig(Settings):
    """World-frame target tracks (`branchrange.onboard.mavlink.world_tracks`), used when vehicle state arrives.

    Each track is a Kalman filter on a static point in local NED. A cut point measured at range r (metres, camera
    frame) by a camera of focal length f (px) and baseline B (m) has a standard deviation of `lateral_sigma_px`·r /
    f across the line of sight and `disparity_sigma_px`·r² / (f·B) along it (a disparity error δ moves the depth by
    Z²·δ / (f·B)): in pixels, so that one setting holds at every resolution — in metres the same σ would be twice
    too small at half the resolution. 0.34 px and 5.1 px are 8.5 mm and 8 mm at 1 m for a ZED Mini at HD720 (f·B ≈
    40 px·m, f ≈ 640 px). A branch the region budget matched s times smaller (near the tree) has both σ multiplied
    by s^`scale_exponent` (its pixels are s times coarser, but its cut point averages over more of them; measured,
    the errors grow about as √s — 0.5 — not as s, the worst case of 1). Both σ are measured, not assumed
    (`benchmarks/cut_point_noise.py`, rendered flights of a scene seed apart from the approach benchmark's, the
    shipped onboard file): the 68th percentile of one cut point's error with the built-in segmenter was 0.34 px
    along the line of sight and 5.1 px across it (in these px, ÷ s^0.5) (its instances' ends move along the branch);
    with truth masks 0.12 and 1.9 px, so σ is wider than their errors — it is set for what flies
    (`benchmarks/approach.py` flies truth masks with their own measured noise). `process_noise_m2_per_s` lets a
    track follow a branch that sways or a slowly drifting local position. A cut point joins the nearest track within
    `gate_m`. A track whose newest cut point was captured more than `stale_after_s` ago is no longer sent
    (occlusions shorter than that are bridged by the filter) and is forgotten after `forget_after_s`. Ages count
    from the capture, so `stale_after_s` must exceed the capture → publish latency (up to 1 s on a CPU companion) by
    a frame or two: 1.5 s.

    Honest covariance: `bias_share` of each cut point's variance is a stereo bias shared by views from
    (nearly) the same viewpoint — within `same_view_deg` of line of sight and `same_view_range_ratio`
    of range — and averages down only over distinct viewpoints, so a hover does not shrink σ below
    the bias at that range (0.3: measured in a hover, 0.24 of the built-in segmenter's error variance is shared
    by its views, `benchmarks/cut_point_noise.py`; `benchmarks/approach.py` reports σ against the actual error).

    The target (`world_tracks.TargetRule`): a track needs `target_min_observations` consistent cut points in a row
    (each within `consistency_m` of the track), a fused 1-σ radius ≤ `target_max_sigma_m` (2 cm: a target off by
    more than 5 cm is then a 2.5-σ event; one view from 2.8 m has a depth σ of ~6 cm, and such a target was once 5.8
    cm off on a rendered approach; without vehicle state, where nothing is fused, one view's σ must be within it:
    ~1.5 m at HD720), and a recency-weighted confidence (weights halve every `confidence_half_life_s`) ≥
    `cutpoints.target_min_confidence`, and its newest cut point must be captured within `mavlink.max_result_age_s`;
    the current target is kept unless another ranks better by `target_switch_margin` (a share of its score under
    `cutpoints.target_policy`).
    """

    section = "tracking"
    error = ConfigError
    limits = {
        "gate_m": Limit(exclusive_minimum=0, expected="metres > 0"),
        "lateral_sigma_px": Limit(exclusive_minimum=0, expected="px > 0"),
        "disparity_sigma_px": Limit(exclusive_minimum=0, expected="px > 0"),
        "process_noise_m2_per_s": Limit(minimum=0, expected="m²/s >= 0"),
        "stale_after_s": Limit(exclusive_minimum=0, expected="seconds > 0"),
        "bias_share": Limit(minimum=0, maximum=0.95, expected="a share in [0, 0.95]"),
        "scale_exponent": Limit(minimum=0, maximum=1, expected="an exponent in [0, 1]"),
        "same_view_deg": Limit(minimum=0, exclusive_maximum=90, expected="degrees in [0, 90)"),
        "same_view_range_ratio": Limit(minimum=0, exclusive_maximum=1, expected="a ratio in [0, 1)"),
        "target_min_observations": Limit(minimum=1, expected="≥ 1 observation"),
        "target_max_sigma_m": Limit(exclusive_minimum=0, expected="metres > 0"),
        "consistency_m": Limit(exclusive_minimum=0, expected="metres > 0"),
        "confidence_half_life_s": Limit(exclusive_minimum=0, expected="seconds > 0"),
        "target_switch_margin": Limit(minimum=0, exclusive_maximum=1, expected="a share in [0, 1)"),
    }

    gate_m: float = 0.15
    lateral_sigma_px: float = 5.1
    disparity_sigma_px: float = 0.34
    process_noise_m2_per_s: float = 1e-5
    scale_exponent: float = 0.5
    stale_after_s: float = 1.5
    forget_after_s: float = 5.0
    bias_share: float = 0.3
    same_view_deg: float = 2.0
    same_view_range_ratio: float = 0.05
    target_min_observations: int = 3
    target_max_sigma_m: float = 0.02
    consistency_m: float = 0.05
    confidence_half_life_s: float = 0.4
    target_switch_margin: float = 0.2

    def checks(self) -> Checks:
        """The rules beyond each key's `Limit`."""
        return {
            "forget_after_s": (
                self.forget_after_s >= self.stale_after_s,
                f"seconds >= tracking.stale_after_s ({self.stale_after_s})",
            ),
        }

    def sigmas_m(
        self, range_m: float, focal_px: float, baseline_m: float, disparity_scale: int = 1
    ) -> tuple[float, float]:
        """(lateral, along the line of sight) 1-σ of a cut point at `range_m` (m), metres, for a camera of
        `focal_px` (px at full resolution) and `baseline_m` (m), its branch matched `disparity_scale` times
        smaller (the region budget; 1: at full resolution)."""
        px = float(disparity_scale) ** self.scale_exponent / focal_px
        return self.lateral_sigma_px * range_m * px, self.disparity_sigma_px * range_m**2 * px / baseline_m


@dataclass(frozen=True)
class ApiConfig(Settings):
    """The HTTP service: address, bearer token and resource limits.

    - `enabled`: the daemon also serves /latest, /health and /metrics (`branchrange serve` always serves).
    - `host`, `port`: the address to listen on; any host but loopback needs a `token`.
    - `token`: the bearer token requests must carry (or BRANCHRANGE_API_TOKEN); empty disables
      authentication, which `branchrange serve` allows on loopback only.
    - `max_upload_mb`: the largest request body; `max_pixels`: the largest image (width × height).
    - `max_concurrency`: inferences that run at once; one more request gets 503 with a `Retry-After`
      of `retry_after_s` seconds instead of waiting in an unbounded queue.
    """

    section = "api"
    error = ConfigError
    limits = {
        "port": Limit(minimum=0, maximum=65535, expected="a TCP port in [0, 65535]"),
        "max_upload_mb": Limit(exclusive_minimum=0, expected="megabytes > 0"),
        "max_pixels": Limit(exclusive_minimum=0, expected="a positive pixel count (width × height)"),
        "max_concurrency": Limit(minimum=1, expected="an integer >= 1"),
        "retry_after_s": Limit(minimum=1, expected="whole seconds >= 1"),
    }

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = 8080
    token: str = ""
    max_upload_mb: float = 20.0
    max_pixels: int = 2208 * 1242
    max_concurrency: int = 1
    retry_after_s: int = 1

    def __post_init__(self) -> None:
        # never echoed: a token with stray spaces is still a secret. Whitespace-only would count as
        # "a token set" and let the service bind a public address while no request could match it.
        if self.token and self.token.strip() != self.token:
            kind = "is whitespace only" if not self.token.strip() else "has leading or trailing whitespace"
            raise ConfigError(
                f"api.token {kind} (or BRANCHRANGE_API_TOKEN): expected a token without "
                "surrounding spaces, or empty for no authentication (loopback only)"
            )
        super().__post_init__()

    @property
    def max_upload_bytes(self) -> int:
        """`max_upload_mb` in bytes (MiB)."""
        return int(self.max_upload_mb * 1024 * 1024)


@dataclass(frozen=True)
class LogConfig(Settings):
    """Where per-frame results go and how often the daemon reports its status.

    - `results_jsonl`: the daemon's results log (a run header line, then one `branchrange/v1` line per
      frame; `branchrange.onboard.results_log`); empty: none.
    - `results_max_mb`: past this size (MiB) the log is rotated — `NAME` becomes `NAME.1`, and a new
      `NAME` starts with the run header again; 0: never. At the onboard rate the log grows about
      56 MB an hour.
    - `results_keep`: rotated files kept (`NAME.1` … `NAME.N`, the oldest deleted): with the defaults at
      most 1.1 GB, about 18 hours of flight.
    - `level`: the daemon's log level (DEBUG, INFO, WARNING, ERROR).
    - `status_interval_s`: seconds between the daemon's status lines.
    """

    section = "log"
    error = ConfigError
    limits = {
        "results_max_mb": Limit(minimum=0, expected="MiB ≥ 0 (0: never rotate)"),
        "results_keep": Limit(minimum=1, expected="at least 1 rotated file"),
        "level": Limit(enum=LOG_LEVELS, expected="DEBUG, INFO, WARNING or ERROR"),
        "status_interval_s": Limit(exclusive_minimum=0, expected="seconds > 0"),
    }

    results_jsonl: str = ""
    results_max_mb: float = 100.0
    results_keep: int = 10
    level: str = "INFO"
    status_interval_s: float = 5.0

    @property
    def results_max_bytes(self) -> int:
        """`results_max_mb` in bytes (MiB)."""
        return int(self.results_max_mb * 1024 * 1024)


@dataclass(frozen=True)
class SheddingConfig(Settings):
    """How the onboard loop sheds work when results near `mavlink.max_result_age_s`
    (`branchrange.onboard.load_shedding`): a companion computer always runs other processes, and a late
    result is worth nothing to the autopilot, so a cheaper result in time beats the full one too late.

    - `enabled`: shed work at all (off: every frame is processed as configured, late or not).
    - `raise_at`: a share of `mavlink.max_result_age_s`; when the median capture → publish time of the last
      `window_frames` results passes it, or one result is late, the next level is taken.
    - `lower_at`: a share of `mavlink.max_result_age_s`; after `calm_frames` results in a row below it, one
      level is given back (a retry that has to be shed again soon waits twice as long the next time).
    - `window_frames`: results whose median is compared with `raise_at`.
    - `calm_frames`: results in a row below `lower_at` before a level is given back.
    - `max_level`: the highest level taken: 1 drops the roi mode's full-resolution instance step
      (`roi.full_resolution_instances`: its ~50 ms a frame on the stereo thread), 2 also each branch's own
      disparity refinement (`stereo.refine_branches`: tens of ms on the geometry thread near the tree).
    """

    section = "shedding"
    error = ConfigError
    limits = {
        # the bound between them (lower_at < raise_at) is a check between keys, not a plain range
        "raise_at": Limit(maximum=1),
        "lower_at": Limit(exclusive_minimum=0),
        "window_frames": Limit(minimum=1, expected="≥ 1 result"),
        "calm_frames": Limit(minimum=1, expected="≥ 1 result"),
        "max_level": Limit(minimum=0, maximum=2, expected="0, 1 or 2"),
    }

    enabled: bool = True
    raise_at: float = 0.7
    lower_at: float = 0.4
    window_frames: int = 5
    calm_frames: int = 30
    max_level: int = 2

    def checks(self) -> Checks:
        """The range of every setting; `lower_at` below `raise_at` (else the level would flap)."""
        return {
            "raise_at": (0 < self.raise_at <= 1, "a share in (0, 1]"),
            "lower_at": (
                0 < self.lower_at < self.raise_at,
                f"a share in (0, shedding.raise_at = {self.raise_at})",
            ),
        }
