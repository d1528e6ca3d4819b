"""BranchRange's one configuration file: TOML sections validated into frozen dataclasses.

Sections: `[camera]`, `[stereo]`, `[roi]`, `[cutpoints]`, `[mavlink]`, `[tracking]`, `[api]`, `[log]`. Every option has a
default, so an empty file is a valid configuration; an unknown key, a value of the wrong type or
out of range raises `ConfigError` naming the key (`mavlink.send_rate_hz`) and what was expected.
Examples live in `deploy/onboard.toml` and `deploy/serve.toml`.

To add an option: add a typed field with a default to its section's dataclass, and a range check
in `__post_init__` if it has one. The loader reads the field list, so nothing else changes.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from branchrange.settings_check import check_physical


class ConfigError(ValueError):
    """A configuration file or value that cannot be used; the message names the key at fault."""


Vector3 = tuple[float, float, float]


def _require(condition: bool, key: str, value: Any, expected: str) -> None:
    """Raise `ConfigError` naming `key` when `condition` is false."""
    if not condition:
        raise ConfigError(f"{key} = {value!r}: expected {expected}")


@dataclass(frozen=True)
class CameraConfig:
    """Where frames come from and how the camera sits on the vehicle.

    `source` is a `camera.sources.open_source` spec; a ZED's mode is part of it
    (`zed:/dev/zedmini:HD720`, HD720 when left out). `calibration` is a calibration file that
    overrides what the source knows (a ZED factory `.conf` is read at the spec's mode).
    `mount_rpy_deg` is the camera's roll, pitch, yaw in degrees relative to a camera looking
    straight ahead (body FRD, right-handed: pitch > 0 tilts the optical axis up, yaw > 0 turns it
    right); `mount_xyz_m` the camera's optical centre in body FRD metres from the vehicle origin.
    `stall_timeout_s`: no frame for this long means the camera is lost (watchdog).
    """

    source: str = "zed:0"
    calibration: str = ""
    mount_rpy_deg: Vector3 = (0.0, 0.0, 0.0)
    mount_xyz_m: Vector3 = (0.0, 0.0, 0.0)
    stall_timeout_s: float = 2.0

    def __post_init__(self) -> None:
        _require(bool(self.source.strip()), "camera.source", self.source, "a source spec such as 'zed:0', 'oak' or 'replay:PATH'")
        _require(self.stall_timeout_s > 0, "camera.stall_timeout_s", self.stall_timeout_s, "seconds > 0")


@dataclass(frozen=True)
class StereoConfig:
    """Which stereo backend computes disparity (`stereo.backends.make_backend` arguments).

    `emcstereo` needs `weights`: a network without them gives meaningless disparities, which the
    daemon would send to the flight controller as cut points. `mode`: 'roi' matches the frame at low
    resolution and each branch at full resolution in its box and disparity window (`[roi]`,
    `branchrange.roi`) — the real-time onboard default; 'full' matches the whole frame.
    """

    backend: str = "sgbm"
    weights: str = ""
    max_disp: int = 192
    device: str = "cpu"
    precision: str = "fp32"
    mode: str = "roi"

    def __post_init__(self) -> None:
        _require(self.mode in ("roi", "full"), "stereo.mode", self.mode,
                 "'roi' (coarse pass + full-resolution regions per branch, see [roi]) or 'full' (whole frame)")
        _require(self.backend in ("sgbm", "emcstereo"), "stereo.backend", self.backend, "'sgbm' or 'emcstereo'")
        _require(self.backend != "emcstereo" or bool(self.weights.strip()), "stereo.weights", self.weights,
                 "a checkpoint path when stereo.backend = 'emcstereo'")
        _require(self.max_disp > 0 and self.max_disp % 16 == 0, "stereo.max_disp", self.max_disp,
                 "a positive multiple of 16 (pixels; SGBM's step, and EMCStereo's cost volume at 1/4 resolution is halved twice)")
        _require(self.precision in ("fp32", "fp16"), "stereo.precision", self.precision, "'fp32' or 'fp16'")


@dataclass(frozen=True)
class RoiConfig:
    """The coarse-to-fine settings of `stereo.mode = "roi"` (`branchrange.roi`; px at full resolution).

    - `coarse_width`: width of the coarse pass in px (frames narrower than 1.5× this are matched
      coarsely at full resolution, scale 1).
    - `box_margin_px`: how far each instance's box grows on every side (the matcher's block and the
      silhouette's edges need context).
    - `window_margin_px`: how far the disparity window grows beyond the instance's coarse range.
    - `max_regions`: only the nearest this many branches (by coarse disparity) get a fine pass
      (the trunk keeps its coarse disparity).
    - `network_regions`: with a network backend (emcstereo), only the nearest this many regions —
      the target's candidates — are matched by the network, the others by SGBM (a network region
      costs about 0.4 s at 200×200 px on 2 CPU cores); 0: every region by the network.
    """

    coarse_width: int = 640
    box_margin_px: int = 16
    window_margin_px: int = 8
    max_regions: int = 12
    network_regions: int = 1

    def __post_init__(self) -> None:
        _require(self.coarse_width >= 64, "roi.coarse_width", self.coarse_width, "at least 64 px")
        _require(0 <= self.box_margin_px <= 256, "roi.box_margin_px", self.box_margin_px, "0..256 px")
        _require(0 <= self.window_margin_px <= 64, "roi.window_margin_px", self.window_margin_px, "0..64 px")
        _require(1 <= self.max_regions <= 256, "roi.max_regions", self.max_regions, "1..256")
        _require(0 <= self.network_regions <= 256, "roi.network_regions", self.network_regions, "0..256 (0: all)")


@dataclass(frozen=True)
class CutpointsConfig:
    """Where on a branch the cut goes and which branch is the target (`branchrange.pipeline`).

    `target_policy`: 'nearest_confident' (distance / confidence), 'nearest', 'most_confident' or
    'thickest' (`branchrange.cutpoints.select_target`); branches below
    `target_min_confidence` are never the target, below `min_confidence` not reported at all.
    `tracking` keeps branch ids stable across frames (the daemon and replay want it).
    `max_instances`: a mask with more branch instances is refused (`MaskError`, HTTP 422) before
    any geometry runs — a frame of branches holds tens, and each instance costs time.
    """

    cut_offset_m: float = 0.05
    min_confidence: float = 0.0
    target_policy: str = "nearest_confident"
    target_min_confidence: float = 0.3
    tracking: bool = True
    max_instances: int = 256

    def __post_init__(self) -> None:
        check_physical("cut_offset_m", self.cut_offset_m, "cutpoints.cut_offset_m", ConfigError)
        _require(0.0 <= self.min_confidence <= 1.0, "cutpoints.min_confidence", self.min_confidence, "a number in [0, 1]")
        from branchrange.cutpoints import TARGET_POLICIES

        _require(self.target_policy in TARGET_POLICIES, "cutpoints.target_policy",
                 self.target_policy, "one of " + ", ".join(repr(p) for p in TARGET_POLICIES))
        _require(0.0 <= self.target_min_confidence <= 1.0, "cutpoints.target_min_confidence",
                 self.target_min_confidence, "a number in [0, 1]")
        _require(self.max_instances >= 1, "cutpoints.max_instances", self.max_instances, "an integer >= 1")


@dataclass(frozen=True)
class MavlinkConfig:
    """The link to the flight controller and what is sent over it (see `branchrange.mavlink`).

    `url` is a pymavlink connection string: `udpout:HOST:PORT`, `udpin:HOST:PORT`,
    `tcp:HOST:PORT`, or a serial device path with `baud`. `signing_key_file` holds the 32-byte
    MAVLink 2 signing key ("" = unsigned). `target_as_obstacle` sends the target branch to the
    autopilot's proximity fence too (off by default: ArduPilot keeps AVOID_MARGIN from every
    obstacle, so the drone would stop short of the branch it must cut). Results older than
    `max_result_age_s` are reported as "no target"; messages go out at least `send_rate_hz` times
    a second even without new results (ArduPilot and PX4 call a proximity sensor stale at 0.5 s).

    Vehicle state and link health (`branchrange.mavlink.vehicle_state`): the autopilot is asked for
    ATTITUDE and LOCAL_POSITION_NED at `state_rate_hz` (MAV_CMD_SET_MESSAGE_INTERVAL) unless
    `request_vehicle_state` is off; the link counts as connected only while the autopilot's
    HEARTBEAT arrives, lost after `heartbeat_timeout_s`; a pose older than `pose_timeout_s` is not
    used (targets then go out in the camera frame of their capture, as without vehicle state).
    `obstacle_min_confidence`: cut points below it are not sent as obstacles (README says why 0.3).
    The approach setpoint (SET_POSITION_TARGET_LOCAL_NED, `branchrange.mavlink.approach`) is off
    unless `setpoint_enabled`: `setpoint_standoff_m` before the cut point, at most
    `setpoint_max_step_m` from the vehicle, moving at most `setpoint_max_speed_m_s`, only for a
    fresh target track with `setpoint_min_observations` and confidence ≥ `setpoint_min_confidence`.
    """

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
    obstacle_min_confidence: float = 0.3
    setpoint_enabled: bool = False
    setpoint_standoff_m: float = 0.6
    setpoint_max_step_m: float = 1.0
    setpoint_max_speed_m_s: float = 0.5
    setpoint_min_observations: int = 5
    setpoint_min_confidence: float = 0.5

    def __post_init__(self) -> None:
        _require(bool(self.url.strip()), "mavlink.url", self.url, "a pymavlink connection string such as 'udpout:127.0.0.1:14550' or '/dev/ttyTHS1'")
        _require(self.baud > 0, "mavlink.baud", self.baud, "a positive baud rate")
        _require(1 <= self.system_id <= 255, "mavlink.system_id", self.system_id, "an integer in [1, 255]")
        _require(1 <= self.component_id <= 255, "mavlink.component_id", self.component_id, "an integer in [1, 255]")
        _require(self.max_result_age_s > 0, "mavlink.max_result_age_s", self.max_result_age_s, "seconds > 0")
        for key in ("min_distance_m", "max_distance_m"):  # the depth band reported to the autopilot
            check_physical("distance_m", getattr(self, key), f"mavlink.{key}", ConfigError)
        _require(self.send_rate_hz >= 2.0, "mavlink.send_rate_hz", self.send_rate_hz, "at least 2 Hz (autopilots call a sensor stale after 0.5 s)")
        _require(0 <= self.min_distance_m < self.max_distance_m, "mavlink.min_distance_m", self.min_distance_m, f"metres >= 0 and below mavlink.max_distance_m ({self.max_distance_m})")
        _require(0 <= self.sensor_id <= 255, "mavlink.sensor_id", self.sensor_id, "an integer in [0, 255]")
        _require(self.reconnect_interval_s > 0, "mavlink.reconnect_interval_s", self.reconnect_interval_s, "seconds > 0")
        _require(1.0 <= self.state_rate_hz <= 100.0, "mavlink.state_rate_hz", self.state_rate_hz, "a rate in [1, 100] Hz")
        _require(self.heartbeat_timeout_s > 0, "mavlink.heartbeat_timeout_s", self.heartbeat_timeout_s, "seconds > 0 (MAVLink's usual is 3)")
        _require(0 < self.pose_timeout_s <= 5.0, "mavlink.pose_timeout_s", self.pose_timeout_s, "seconds in (0, 5]")
        _require(0.0 <= self.obstacle_min_confidence <= 1.0, "mavlink.obstacle_min_confidence", self.obstacle_min_confidence, "a number in [0, 1]")
        _require(self.setpoint_standoff_m >= 0, "mavlink.setpoint_standoff_m", self.setpoint_standoff_m, "metres >= 0")
        _require(self.setpoint_max_step_m > 0, "mavlink.setpoint_max_step_m", self.setpoint_max_step_m, "metres > 0")
        _require(0 < self.setpoint_max_speed_m_s <= 5.0, "mavlink.setpoint_max_speed_m_s", self.setpoint_max_speed_m_s, "a speed in (0, 5] m/s")
        _require(self.setpoint_min_observations >= 1, "mavlink.setpoint_min_observations", self.setpoint_min_observations, "an integer >= 1")
        _require(0.0 <= self.setpoint_min_confidence <= 1.0, "mavlink.setpoint_min_confidence", self.setpoint_min_confidence, "a number in [0, 1]")


@dataclass(frozen=True)
class TrackingConfig:
    """World-frame target tracks (`branchrange.mavlink.world_tracks`), used when vehicle state arrives.

    Each track is a Kalman filter on a static point in local NED. A cut point measured at range r
    (metres, camera frame) has a standard deviation of `lateral_sigma_at_1m_m`·r across the line of
    sight and `depth_sigma_at_1m_m`·r² along it (stereo depth error grows with the square of the
    range); `process_noise_m2_per_s` lets a track follow a branch that sways or a slowly drifting
    local position. A cut point joins the nearest track within `gate_m`. A track whose newest
    cut point was captured more than `stale_after_s` ago is no longer sent (occlusions shorter than
    that are bridged by the filter) and is forgotten after `forget_after_s`. Ages count from the
    capture, so `stale_after_s` must exceed the capture → publish latency (up to 1 s on a CPU
    companion) by a frame or two: 1.5 s.
    """

    gate_m: float = 0.15
    lateral_sigma_at_1m_m: float = 0.004
    depth_sigma_at_1m_m: float = 0.01
    process_noise_m2_per_s: float = 1e-5
    stale_after_s: float = 1.5
    forget_after_s: float = 5.0

    def __post_init__(self) -> None:
        _require(self.gate_m > 0, "tracking.gate_m", self.gate_m, "metres > 0")
        _require(self.lateral_sigma_at_1m_m > 0, "tracking.lateral_sigma_at_1m_m", self.lateral_sigma_at_1m_m, "metres > 0")
        _require(self.depth_sigma_at_1m_m > 0, "tracking.depth_sigma_at_1m_m", self.depth_sigma_at_1m_m, "metres > 0")
        _require(self.process_noise_m2_per_s >= 0, "tracking.process_noise_m2_per_s", self.process_noise_m2_per_s, "m²/s >= 0")
        _require(self.stale_after_s > 0, "tracking.stale_after_s", self.stale_after_s, "seconds > 0")
        _require(self.forget_after_s >= self.stale_after_s, "tracking.forget_after_s", self.forget_after_s,
                 f"seconds >= tracking.stale_after_s ({self.stale_after_s})")


@dataclass(frozen=True)
class ApiConfig:
    """The HTTP service: address, bearer token and resource limits.

    An empty `token` disables authentication, which `branchrange serve` allows on loopback only.
    `max_concurrency` inferences run at once; one more request gets 503 with `Retry-After:
    retry_after_s` instead of waiting in an unbounded queue.
    """

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
            raise ConfigError(f"api.token {kind} (or BRANCHRANGE_API_TOKEN): expected a token without "
                              "surrounding spaces, or empty for no authentication (loopback only)")
        _require(0 <= self.port <= 65535, "api.port", self.port, "a TCP port in [0, 65535]")
        _require(self.max_upload_mb > 0, "api.max_upload_mb", self.max_upload_mb, "megabytes > 0")
        _require(self.max_pixels > 0, "api.max_pixels", self.max_pixels, "a positive pixel count (width × height)")
        _require(self.max_concurrency >= 1, "api.max_concurrency", self.max_concurrency, "an integer >= 1")
        _require(self.retry_after_s >= 1, "api.retry_after_s", self.retry_after_s, "whole seconds >= 1")

    @property
    def max_upload_bytes(self) -> int:
        """`max_upload_mb` in bytes (MiB)."""
        return int(self.max_upload_mb * 1024 * 1024)


@dataclass(frozen=True)
class LogConfig:
    """Where per-frame results go and how often the daemon reports its status."""

    results_jsonl: str = ""
    level: str = "INFO"
    status_interval_s: float = 5.0

    def __post_init__(self) -> None:
        _require(self.level in ("DEBUG", "INFO", "WARNING", "ERROR"), "log.level", self.level, "DEBUG, INFO, WARNING or ERROR")
        _require(self.status_interval_s > 0, "log.status_interval_s", self.status_interval_s, "seconds > 0")


@dataclass(frozen=True)
class SegmenterSection:
    """Which segmenter finds branches when no mask is given (`branchrange.segmentation.choose`).

    `model`: 'structure' (built in, 3D structure), 'geometric' (the older built-in one) or
    'onnx:FILE' (your ONNX model, YOLOv8-seg or per-pixel logits); `branch_classes` / `trunk_classes`: the model's class ids for branch and trunk;
    `score_threshold`: detections scoring lower are dropped.
    """

    model: str = "structure"
    branch_classes: tuple[int, ...] = (0,)
    trunk_classes: tuple[int, ...] = ()
    score_threshold: float = 0.25

    def __post_init__(self) -> None:
        from branchrange.segmentation.choose import check_segmenter_name

        try:
            check_segmenter_name(self.model)
            self.onnx_settings()
        except ValueError as exc:
            raise ConfigError(str(exc)) from None

    def onnx_settings(self) -> Any:
        """The `OnnxSegmenterConfig` these options describe."""
        from branchrange.segmentation.onnx_model import OnnxSegmenterConfig

        return OnnxSegmenterConfig(branch_classes=self.branch_classes, trunk_classes=self.trunk_classes,
                                   score_threshold=self.score_threshold)


@dataclass(frozen=True)
class Config:
    """The whole configuration, one dataclass per TOML section."""

    camera: CameraConfig = field(default_factory=CameraConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    roi: RoiConfig = field(default_factory=RoiConfig)
    cutpoints: CutpointsConfig = field(default_factory=CutpointsConfig)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    api: ApiConfig = field(default_factory=ApiConfig)
    log: LogConfig = field(default_factory=LogConfig)
    segmenter: SegmenterSection = field(default_factory=SegmenterSection)


def _coerce(key: str, value: Any, annotation: Any) -> Any:
    """Check one TOML value against a field's type; ints are accepted where floats are expected."""
    if annotation is bool:
        _require(isinstance(value, bool), key, value, "true or false")
        return value
    if annotation is int:
        _require(isinstance(value, int) and not isinstance(value, bool), key, value, "an integer")
        return value
    if annotation is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        _require(ok, key, value, "a finite number")
        return float(value)
    if annotation is str:
        _require(isinstance(value, str), key, value, "a string")
        return value
    if typing.get_origin(annotation) is tuple and typing.get_args(annotation)[1:] == (Ellipsis,):
        item = typing.get_args(annotation)[0]
        _require(isinstance(value, list), key, value, "a list")
        return tuple(_coerce(f"{key}[{i}]", v, item) for i, v in enumerate(value))
    if typing.get_origin(annotation) is tuple:
        items = typing.get_args(annotation)
        ok = isinstance(value, list) and len(value) == len(items)
        _require(ok, key, value, f"a list of {len(items)} numbers")
        return tuple(_coerce(f"{key}[{i}]", v, t) for i, (v, t) in enumerate(zip(value, items)))
    raise TypeError(f"config field {key} has an unsupported type {annotation!r}")


def _section(cls: type, name: str, table: Any) -> Any:
    """Build section dataclass `cls` from TOML table `table`, rejecting unknown keys."""
    _require(isinstance(table, dict), name, table, f"a table [{name}]")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ConfigError(f"{name}.{unknown[0]}: unknown option; [{name}] takes {', '.join(sorted(known))}")
    return cls(**{key: _coerce(f"{name}.{key}", value, hints[key]) for key, value in table.items()})


def config_from_dict(data: dict[str, Any]) -> Config:
    """Validate a parsed TOML document into a `Config`; raises `ConfigError` naming the key."""
    sections = {f.name: typing.get_type_hints(Config)[f.name] for f in dataclasses.fields(Config)}
    unknown = sorted(set(data) - set(sections))
    if unknown:
        raise ConfigError(f"[{unknown[0]}]: unknown section; the file takes {', '.join(f'[{s}]' for s in sections)}")
    return Config(**{name: _section(cls, name, data[name]) for name, cls in sections.items() if name in data})


def load_config(path: str | Path | None) -> Config:
    """Read and validate a TOML configuration file; `None` gives the defaults."""
    if path is None:
        return Config()
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: configuration file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def pipeline_config(cfg: Config) -> Any:
    """The `branchrange.pipeline.PipelineConfig` that `[stereo]`, `[cutpoints]` and `[segmenter]` describe."""
    from branchrange.cutpoints import CutPointConfig
    from branchrange.pipeline import PipelineConfig

    s, c = cfg.stereo, cfg.cutpoints
    return PipelineConfig(
        backend=s.backend, weights=s.weights or None, max_disp=s.max_disp, device=s.device,
        precision=s.precision, target_policy=c.target_policy,
        target_min_confidence=c.target_min_confidence, tracking=c.tracking,
        cutpoints=CutPointConfig(cut_offset_m=c.cut_offset_m, min_confidence=c.min_confidence,
                                 max_instances=c.max_instances),
        mode=s.mode, roi=cfg.roi,
        segmenter_name=cfg.segmenter.model, onnx_segmenter=cfg.segmenter.onnx_settings())
