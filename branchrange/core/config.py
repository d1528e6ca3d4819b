"""BranchRange's one configuration file: each TOML section is the settings dataclass its code uses.

| section | dataclass | used by |
|---|---|---|
| `[camera]` | `CameraConfig` | the daemon's frame source, its mount and watchdog |
| `[stereo]` | `StereoConfig` | `Pipeline.backend` (`stereo.backends.make_backend`), roi or full mode |
| `[roi]` | `RoiConfig` | `branchrange.core.roi.CoarseToFine` |
| `[cutpoints]` | `branchrange.core.cutpoints.CutPointConfig` | cut-point estimation, target choice, tracking on/off |
| `[branch_tracking]` | `branchrange.core.tracking.TrackerConfig` | the per-frame branch ids (`BranchTracker`) |
| `[masks]` | `MaskConfig` | how mask files and arrays are read |
| `[segmenter]` | `SegmenterConfig` (+ `[segmenter.structure]`, `[segmenter.geometric]`) | `SegmenterConfig.build` |
| `[mavlink]` | `MavlinkConfig` | `branchrange.onboard.mavlink.MavlinkRelay` |
| `[tracking]` | `TrackingConfig` | world-frame target tracks (`branchrange.onboard.mavlink.world_tracks`) |
| `[api]` | `ApiConfig` | the HTTP service |
| `[log]` | `LogConfig` | the results log and status reports |

The pipeline's sections reach it together as `pipeline_config(cfg)`, which hands over the section
objects themselves. Every option has a default, so an empty file is a valid configuration. Every
option can be set in the file and on the command line (`--set section.key=value`, a TOML value;
`--set segmenter.structure.max_range_m=3`); an unknown key, a value of the wrong type or out of
range raises `ConfigError` naming the key (`mavlink.send_rate_hz`) and what was expected.
Examples live in `deploy/*.toml`.

To add an option: add a typed field with a default to its section's dataclass, its range to that
class's `checks()` and its plain bounds or choices to its `limits` (`branchrange.core.settings_check`),
and say what it does in a bullet of the class docstring (`branchrange.core.settings_docs`). The
loader reads the field list; a field whose type is itself a settings dataclass is a sub-table. The
JSON Schema that editors check the file with and the reference `docs/configuration.md` are
generated from the same classes (`branchrange config schema`, `branchrange config reference`); tests
say when they need regenerating.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import tomllib
import typing
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from branchrange.core.cutpoints import CutPointConfig
from branchrange.core.masks import DEFAULT_IGNORED_IDS, DEFAULT_TRUNK_ID
from branchrange.core.segmentation.choose import (
    DEFAULT_SEGMENTER,
    SEGMENTER_NAMES,
    check_segmenter_name,
    make_segmenter,
)
from branchrange.core.segmentation.learned import LearnedSegmenterConfig
from branchrange.core.segmentation.onnx_model import OnnxSegmenterConfig
from branchrange.core.segmentation.segmenter import GeometricSegmenterConfig, Segmenter
from branchrange.core.segmentation.structure import StructureSegmenterConfig
from branchrange.core.settings_check import Checks, Limit, Settings, SettingsError, in_physical_range
from branchrange.core.tracking import TrackerConfig
from stereo.backends import (
    BACKEND_NAMES,
    MAX_DISP_EXPECTED,
    PRECISIONS,
    WEIGHTED_BACKENDS,
    StereoBackend,
    is_valid_max_disp,
)
from stereo.backends.base import MAX_DISP_LIMIT, MAX_DISP_STEP


class ConfigError(SettingsError):
    """A configuration file or value that cannot be used; the message names the key at fault."""


#: `stereo.mode`: 'full' matches the whole frame at full resolution; 'roi' coarse-to-fine (`branchrange.core.roi`).
STEREO_MODES: tuple[str, ...] = ("full", "roi")
#: `masks.kind`: how a mask file or array is read (`branchrange.core.masks.masks_from_array`).
MASK_KINDS: tuple[str, ...] = ("auto", "instance", "binary")
#: `log.level`: the logging levels the daemon and the service accept.
LOG_LEVELS: tuple[str, ...] = ("DEBUG", "INFO", "WARNING", "ERROR")


def _one_of(choices: Iterable[str]) -> str:
    """'a', 'b' or 'c' — the accepted values of a setting, for messages."""
    quoted = [repr(c) for c in choices]
    return ", ".join(quoted[:-1]) + f" or {quoted[-1]}" if len(quoted) > 1 else quoted[0]


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
    limits = {"stall_timeout_s": Limit(exclusive_minimum=0)}

    source: str = "zed:0"
    calibration: str = ""
    mount_rpy_deg: Vector3 = (0.0, 0.0, 0.0)
    mount_xyz_m: Vector3 = (0.0, 0.0, 0.0)
    stall_timeout_s: float = 2.0

    def checks(self) -> Checks:
        """The range of every setting."""
        return {
            "source": (bool(self.source.strip()), "a source spec such as 'zed:0', 'oak' or 'replay:PATH'"),
            "stall_timeout_s": (self.stall_timeout_s > 0, "seconds > 0"),
        }


@dataclass(frozen=True)
class StereoConfig(Settings):
    """Which stereo backend computes disparity (`stereo.backends.make_backend` arguments), and how.

    `backend`: one of `stereo.backends.BACKEND_NAMES`. `emcstereo` and `onnx` need `weights` (a
    checkpoint; the exported .onnx file): a network without them gives meaningless disparities,
    which the daemon would send to the flight controller as cut points. `max_disp`: the disparity
    search range in px at full resolution (`stereo.backends.check_max_disp`'s rule). `precision`:
    one of `stereo.backends.PRECISIONS` (fp16/bf16 need a CUDA `device` and emcstereo). `device`: the torch
    device a network backend runs on ('cpu', 'cuda', 'cuda:1'). `mode`:
    'roi' matches the frame at low resolution and each branch at full resolution in its box and
    disparity window (`[roi]`, `branchrange.core.roi`) — the real-time onboard default; 'full' matches
    the whole frame. `verify_weights`: check a registered release's weights against its SHA-256 on load.
    `refine_branches`: once the masks are known, match each branch on its own pixels for a sub-pixel
    disparity free of the background's pull (`branchrange.core.branch_disparity`; ~1 ms per branch).
    """

    section = "stereo"
    error = ConfigError
    limits = {
        "backend": Limit(enum=BACKEND_NAMES),
        "max_disp": Limit(minimum=MAX_DISP_STEP, maximum=MAX_DISP_LIMIT, multiple_of=MAX_DISP_STEP),
        "precision": Limit(enum=PRECISIONS),
        "mode": Limit(enum=STEREO_MODES),
    }

    backend: str = "sgbm"
    weights: str = ""
    max_disp: int = 192
    device: str = "cpu"
    precision: str = "fp32"
    mode: str = "roi"
    verify_weights: bool = True
    refine_branches: bool = True

    def checks(self) -> Checks:
        """The backend, its weights, search range and precision, and the mode."""
        return {
            "mode": (
                self.mode in STEREO_MODES,
                "'roi' (coarse pass + full-resolution regions per branch, see [roi]) or 'full' (whole frame)",
            ),
            "backend": (self.backend in BACKEND_NAMES, _one_of(BACKEND_NAMES)),
            "weights": (
                self.backend not in WEIGHTED_BACKENDS or bool(self.weights.strip()),
                f"a checkpoint path when stereo.backend = {self.backend!r}",
            ),
            "max_disp": (is_valid_max_disp(self.max_disp), MAX_DISP_EXPECTED),
            "precision": (self.precision in PRECISIONS, _one_of(PRECISIONS)),
        }

    def build_backend(self) -> StereoBackend:
        """The `stereo.backends` backend these settings name (`make_backend`); weights whose file name is a
        registered release are checked against its SHA-256 unless `verify_weights` is false (a local file
        that kept a release's name)."""
        from stereo.backends import make_backend

        return make_backend(
            self.backend,
            weights=self.weights_path,
            max_disp=self.max_disp,
            device=self.device,
            precision=self.precision,
            verify_sha256=self.verify_weights,
        )

    @property
    def weights_path(self) -> str | None:
        """`weights` as `make_backend` takes it (None when empty)."""
        return self.weights or None


@dataclass(frozen=True)
class RoiConfig(Settings):
    """The coarse-to-fine settings of `stereo.mode = "roi"` (`branchrange.core.roi`; px at full resolution).

    - `coarse_width`: width of the coarse pass in px (frames narrower than 1.5× this are matched
      coarsely at full resolution, scale 1).
    - `box_margin_px`: how far each instance's box grows on every side (the matcher's block and the
      silhouette's edges need context).
    - `window_margin_px`: how far the disparity window grows beyond the instance's coarse range.
    - `max_regions`: only the nearest this many branches (by coarse disparity) get a fine pass
      (the trunk keeps its coarse disparity); the others are dropped. A bound on a pathological frame,
      not a budget: an SGBM region costs ~1–2 ms, and the learned segmenter gives more than 12 instances
      (fragments and doubtful pieces too) in a quarter of the calibration frames and up to 38 — with 12
      (the setting until 2026-11-26) the pipeline at HD720 lost 7–12 points of recall (benchmarks/RESULTS.md).
    - `network_regions`: with a network backend (emcstereo), only the nearest this many regions —
      the target's candidates — are matched by the network, the others by SGBM (a network region
      costs about 0.4 s at 200×200 px on 2 CPU cores); 0: every region by the network.
    - `full_resolution_instances`: with the learned segmenter, once the regions are matched its instance
      step runs again at full resolution (`LearnedSegmenter.instances`: the coarse look's class
      probabilities brought to full resolution, each branch's fine disparity, the coarse one around it),
      so branches are cut apart at full-resolution depth jumps and their silhouettes are full-resolution
      ones; off = the coarse instances brought up (`roi.refine_labels`). The network still runs once, on the
      coarse frame. On 240 held-out scenes at HD720 recall within 5 cm 65 → 68 % looking once and 70 → 76 %
      with the default second look; on the synthetic HD720 flight (2 cores, one look) a target in 97–100
      instead of 80–85 % of the frames, for ~42 ms a frame on the stereo thread: 5.6–6.1 instead of 8.7–9.6
      fresh results a second (benchmarks/RESULTS.md).
    - `keyframe_interval_s`: with the segmenter (no masks given), run it on keyframes only, this far apart
      (s), and carry each branch's mask over to the frames between by image alignment
      (`branchrange.core.keyframes`); 0: the segmenter on every frame.
    - `track_search_px`: how far (px at full resolution) a carried branch is searched from where it was.
    - `track_min_ncc`: the image match's score (normalised cross-correlation) a carried branch needs;
      under it the branch is lost and the next frame is a keyframe.
    - `track_min_support`: the share of a carried branch's pixels the new frame's disparity must keep (within
      its window); under it the branch was carried to the wrong place: left out, and a keyframe is due.
    - `track_gate_px`: how far (px) a carried branch's disparity may move from the range its pixels had in
      the last frame (median ± 3 robust σ) before the search window's margin: one frame's motion near the tree.
    - `track_max_jump_m`: a carried branch's cut point more than this far (m, camera frame) from its own in
      the last frame is dropped and a keyframe is due: a carried mask that slid onto other pixels (a
      silhouette with much background, the fit taking the background's depth) gives a cut point far off,
      and a tracked result must never jump (one frame's motion at 0.8 m/s moves it 5 cm).
    - `budget`: the region budget (`branchrange.core.region_budget`): each branch's region is matched at the
      coarsest working scale (1, 2, 4 … times smaller) its cut point can afford, and the frame's regions within
      the two caps below; false: every region at full resolution.
    - `budget_min_disparity_px`: a region is shrunk only while its branch's disparity at the working scale stays
      ≥ this (px): relative depth precision σ_d/d at least that of a full-resolution branch at this disparity
      (16 px at HD720 with the ZED Mini is ~2.5 m; regions shrink from ~1.3 m in).
    - `budget_min_diameter_px`: … and while the branch's width at the working scale stays ≥ this (px): a stem the
      matcher still sees (this one is never relaxed to meet the caps).
    - `budget_max_scale`: the coarsest working scale (a power of two; 1: the budget never shrinks a region).
    - `budget_max_pixels`: the frame's region pixels at their working scales at most (px); over it, regions are
      shrunk further nearest-first (the disparity rule gives way, the width rule does not), then the farthest
      are left out. 120,000: above every frame of the rendered HD720 approaches under the two rules (p95 100k,
      max 112k; 156k before the budget), so it bounds a pathological frame (a dense tree close up) and
      never costs a branch on those.
    - `budget_max_cost_mpd`: the frame's matching cost at most, in million pixel-disparities (Σ region pixels ×
      disparities searched, at the working scales): SGBM's time is proportional to it. 6: the same approaches
      need at most 4.75 (p95 4.2; 9.1 before the budget).
    - `budget_trunk_points`: the trunk's cylinder (fitted on the coarse pass) takes at most about this many of its
      pixels (every k-th); 0 (the default): all of them. Its mask grows from ~11,000 coarse px at 3 m to ~41,000
      at 0.8 m at HD720, so deploy/onboard_cpu.toml sets 12,000: near the tree it is fitted on as many points
      as at the start of the approach, each with far less depth noise (the same cut points, the stage flat).
      The count depends on the coarse pass's size, hence no default for every camera.
    - `keyframe_worker`: run the keyframes' segmenter in its own worker (`branchrange.core.keyframe_worker`):
      the stereo thread never waits for it and carries its instances, a few frames old when they arrive, to
      its newest frame; false: a keyframe runs on the stereo thread (as slow as a frame without keyframes).
      Experimental, not for flight: on a quiet 2-core machine its keyframes arrived 0.6–0.9 s old and 10 %
      (0.3 m/s approach) to 38 % (0.8 m/s with 20 °/s yaw) of its targets were false
      (`benchmarks/results/realtime.md`, 2026-11-28 22:05).
    - `track_max_age_s`: with the worker, a track whose keyframe is older than this (s) is dropped (the
      worker is slow, failed or being restarted): its branch goes unreported rather than guessed.
    """

    section = "roi"
    error = ConfigError
    limits = {
        "coarse_width": Limit(minimum=64),
        "box_margin_px": Limit(minimum=0, maximum=256),
        "window_margin_px": Limit(minimum=0, maximum=64),
        "max_regions": Limit(minimum=1, maximum=256),
        "network_regions": Limit(minimum=0, maximum=256),
        "keyframe_interval_s": Limit(minimum=0, maximum=10),
        "track_search_px": Limit(minimum=1, maximum=256),
        "track_min_ncc": Limit(minimum=-1, maximum=1),
        "track_min_support": Limit(minimum=0, maximum=1),
        "track_gate_px": Limit(minimum=0, maximum=64),
        "track_max_jump_m": Limit(exclusive_minimum=0),
        "budget_min_disparity_px": Limit(minimum=1, maximum=256),
        "budget_min_diameter_px": Limit(minimum=1, maximum=64),
        "budget_max_scale": Limit(minimum=1, maximum=8),
        "budget_max_pixels": Limit(minimum=1000),
        "budget_max_cost_mpd": Limit(exclusive_minimum=0),
        "budget_trunk_points": Limit(minimum=0),
        "track_max_age_s": Limit(exclusive_minimum=0, maximum=10),
    }

    coarse_width: int = 640
    box_margin_px: int = 16
    window_margin_px: int = 8
    max_regions: int = 48
    network_regions: int = 1
    full_resolution_instances: bool = True
    keyframe_interval_s: float = 0.0
    track_search_px: int = 32
    track_min_ncc: float = 0.6
    track_min_support: float = 0.5
    track_gate_px: float = 2.0
    track_max_jump_m: float = 0.1
    budget: bool = True
    budget_min_disparity_px: float = 16.0
    budget_min_diameter_px: float = 4.0
    budget_max_scale: int = 4
    budget_max_pixels: int = 120_000
    budget_max_cost_mpd: float = 6.0
    budget_trunk_points: int = 0
    keyframe_worker: bool = False
    track_max_age_s: float = 0.5

    def checks(self) -> Checks:
        """The range of every setting."""
        return {
            "coarse_width": (self.coarse_width >= 64, "at least 64 px"),
            "box_margin_px": (0 <= self.box_margin_px <= 256, "0..256 px"),
            "window_margin_px": (0 <= self.window_margin_px <= 64, "0..64 px"),
            "max_regions": (1 <= self.max_regions <= 256, "1..256"),
            "network_regions": (0 <= self.network_regions <= 256, "0..256 (0: all)"),
            "keyframe_interval_s": (0 <= self.keyframe_interval_s <= 10, "seconds in [0, 10] (0: every frame)"),
            "track_search_px": (1 <= self.track_search_px <= 256, "1..256 px"),
            "track_min_ncc": (-1 <= self.track_min_ncc <= 1, "a score in [-1, 1]"),
            "track_min_support": (0 <= self.track_min_support <= 1, "a share in [0, 1]"),
            "track_gate_px": (0 <= self.track_gate_px <= 64, "px in [0, 64]"),
            "track_max_jump_m": (self.track_max_jump_m > 0, "metres > 0"),
            "budget_min_disparity_px": (1 <= self.budget_min_disparity_px <= 256, "px in [1, 256]"),
            "budget_min_diameter_px": (1 <= self.budget_min_diameter_px <= 64, "px in [1, 64]"),
            "budget_max_scale": (self.budget_max_scale in (1, 2, 4, 8), "1, 2, 4 or 8"),
            "budget_max_pixels": (self.budget_max_pixels >= 1000, "at least 1000 px"),
            "budget_max_cost_mpd": (self.budget_max_cost_mpd > 0, "million pixel-disparities > 0"),
            "budget_trunk_points": (self.budget_trunk_points >= 0, "a count ≥ 0 (0: every pixel)"),
            "track_max_age_s": (0 < self.track_max_age_s <= 10, "seconds in (0, 10]"),
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
        "baud": Limit(exclusive_minimum=0),
        "system_id": Limit(minimum=1, maximum=255),
        "component_id": Limit(minimum=1, maximum=255),
        "max_result_age_s": Limit(exclusive_minimum=0),
        "send_rate_hz": Limit(minimum=2.0),
        "min_distance_m": Limit.physical("distance_m"),
        "max_distance_m": Limit.physical("distance_m"),
        "sensor_id": Limit(minimum=0, maximum=255),
        "reconnect_interval_s": Limit(exclusive_minimum=0),
        "state_rate_hz": Limit(minimum=1.0, maximum=100.0),
        "heartbeat_timeout_s": Limit(exclusive_minimum=0),
        "pose_timeout_s": Limit(exclusive_minimum=0, maximum=5.0),
        "obstacle_min_confidence": Limit(minimum=0.0, maximum=1.0),
        "setpoint_standoff_m": Limit(minimum=0),
        "setpoint_max_step_m": Limit(exclusive_minimum=0),
        "setpoint_max_speed_m_s": Limit(exclusive_minimum=0, maximum=5.0),
        "setpoint_min_observations": Limit(minimum=1),
        "setpoint_min_confidence": Limit(minimum=0.0, maximum=1.0),
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
            "baud": (self.baud > 0, "a positive baud rate"),
            "system_id": (1 <= self.system_id <= 255, "an integer in [1, 255]"),
            "component_id": (1 <= self.component_id <= 255, "an integer in [1, 255]"),
            "max_result_age_s": (self.max_result_age_s > 0, "seconds > 0"),
            "send_rate_hz": (self.send_rate_hz >= 2.0, "at least 2 Hz (autopilots call a sensor stale after 0.5 s)"),
            "max_distance_m": (far_ok, distances),
            "min_distance_m": (
                near_ok and self.min_distance_m < self.max_distance_m,
                f"metres >= 0 and below mavlink.max_distance_m ({self.max_distance_m})",
            ),
            "sensor_id": (0 <= self.sensor_id <= 255, "an integer in [0, 255]"),
            "reconnect_interval_s": (self.reconnect_interval_s > 0, "seconds > 0"),
            "state_rate_hz": (1.0 <= self.state_rate_hz <= 100.0, "a rate in [1, 100] Hz"),
            "heartbeat_timeout_s": (self.heartbeat_timeout_s > 0, "seconds > 0 (MAVLink's usual is 3)"),
            "pose_timeout_s": (0 < self.pose_timeout_s <= 5.0, "seconds in (0, 5]"),
            "obstacle_min_confidence": (0.0 <= self.obstacle_min_confidence <= 1.0, "a number in [0, 1]"),
            "setpoint_standoff_m": (self.setpoint_standoff_m >= 0, "metres >= 0"),
            "setpoint_max_step_m": (self.setpoint_max_step_m > 0, "metres > 0"),
            "setpoint_max_speed_m_s": (0 < self.setpoint_max_speed_m_s <= 5.0, "a speed in (0, 5] m/s"),
            "setpoint_min_observations": (self.setpoint_min_observations >= 1, "an integer >= 1"),
            "setpoint_min_confidence": (0.0 <= self.setpoint_min_confidence <= 1.0, "a number in [0, 1]"),
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
        "gate_m": Limit(exclusive_minimum=0),
        "lateral_sigma_px": Limit(exclusive_minimum=0),
        "disparity_sigma_px": Limit(exclusive_minimum=0),
        "process_noise_m2_per_s": Limit(minimum=0),
        "stale_after_s": Limit(exclusive_minimum=0),
        "bias_share": Limit(minimum=0, maximum=0.95),
        "scale_exponent": Limit(minimum=0, maximum=1),
        "same_view_deg": Limit(minimum=0, exclusive_maximum=90),
        "same_view_range_ratio": Limit(minimum=0, exclusive_maximum=1),
        "target_min_observations": Limit(minimum=1),
        "target_max_sigma_m": Limit(exclusive_minimum=0),
        "consistency_m": Limit(exclusive_minimum=0),
        "confidence_half_life_s": Limit(exclusive_minimum=0),
        "target_switch_margin": Limit(minimum=0, exclusive_maximum=1),
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
        """The range of every setting."""
        return {
            "gate_m": (self.gate_m > 0, "metres > 0"),
            "lateral_sigma_px": (self.lateral_sigma_px > 0, "px > 0"),
            "disparity_sigma_px": (self.disparity_sigma_px > 0, "px > 0"),
            "process_noise_m2_per_s": (self.process_noise_m2_per_s >= 0, "m²/s >= 0"),
            "stale_after_s": (self.stale_after_s > 0, "seconds > 0"),
            "forget_after_s": (
                self.forget_after_s >= self.stale_after_s,
                f"seconds >= tracking.stale_after_s ({self.stale_after_s})",
            ),
            "bias_share": (0 <= self.bias_share <= 0.95, "a share in [0, 0.95]"),
            "scale_exponent": (0 <= self.scale_exponent <= 1, "an exponent in [0, 1]"),
            "same_view_deg": (0 <= self.same_view_deg < 90, "degrees in [0, 90)"),
            "same_view_range_ratio": (0 <= self.same_view_range_ratio < 1, "a ratio in [0, 1)"),
            "target_min_observations": (self.target_min_observations >= 1, "≥ 1 observation"),
            "target_max_sigma_m": (self.target_max_sigma_m > 0, "metres > 0"),
            "consistency_m": (self.consistency_m > 0, "metres > 0"),
            "confidence_half_life_s": (self.confidence_half_life_s > 0, "seconds > 0"),
            "target_switch_margin": (0 <= self.target_switch_margin < 1, "a share in [0, 1)"),
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
        "port": Limit(minimum=0, maximum=65535),
        "max_upload_mb": Limit(exclusive_minimum=0),
        "max_pixels": Limit(exclusive_minimum=0),
        "max_concurrency": Limit(minimum=1),
        "retry_after_s": Limit(minimum=1),
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

    def checks(self) -> Checks:
        """The range of every setting but the token (checked without echoing it)."""
        return {
            "port": (0 <= self.port <= 65535, "a TCP port in [0, 65535]"),
            "max_upload_mb": (self.max_upload_mb > 0, "megabytes > 0"),
            "max_pixels": (self.max_pixels > 0, "a positive pixel count (width × height)"),
            "max_concurrency": (self.max_concurrency >= 1, "an integer >= 1"),
            "retry_after_s": (self.retry_after_s >= 1, "whole seconds >= 1"),
        }

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
        "results_max_mb": Limit(minimum=0),
        "results_keep": Limit(minimum=1),
        "level": Limit(enum=LOG_LEVELS),
        "status_interval_s": Limit(exclusive_minimum=0),
    }

    results_jsonl: str = ""
    results_max_mb: float = 100.0
    results_keep: int = 10
    level: str = "INFO"
    status_interval_s: float = 5.0

    def checks(self) -> Checks:
        """The range of every setting."""
        return {
            "results_max_mb": (self.results_max_mb >= 0, "MiB ≥ 0 (0: never rotate)"),
            "results_keep": (self.results_keep >= 1, "at least 1 rotated file"),
            "level": (self.level in LOG_LEVELS, "DEBUG, INFO, WARNING or ERROR"),
            "status_interval_s": (self.status_interval_s > 0, "seconds > 0"),
        }

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
        "window_frames": Limit(minimum=1),
        "calm_frames": Limit(minimum=1),
        "max_level": Limit(minimum=0, maximum=2),
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
            "window_frames": (self.window_frames >= 1, "≥ 1 result"),
            "calm_frames": (self.calm_frames >= 1, "≥ 1 result"),
            "max_level": (0 <= self.max_level <= 2, "0, 1 or 2"),
        }


@dataclass(frozen=True)
class MaskConfig(Settings):
    """How instance masks (files, arrays, recordings' masks) are read (`branchrange.core.masks.masks_from_array`).

    `trunk_id`: the trunk's id in instance masks (1..65535); `ignored_ids`: ids that are neither
    branch nor trunk (twigs, leaves); `kind`: 'auto' (binary when the mask holds only 0 and one
    value), 'instance' or 'binary' (connected components are the instances).
    """

    section = "masks"
    error = ConfigError
    limits = {
        "trunk_id": Limit(minimum=1, maximum=65535),
        "ignored_ids": Limit(minimum=1, maximum=65535),
        "kind": Limit(enum=MASK_KINDS),
    }

    trunk_id: int = DEFAULT_TRUNK_ID
    ignored_ids: tuple[int, ...] = DEFAULT_IGNORED_IDS
    kind: str = "auto"

    def checks(self) -> Checks:
        """The range of every setting."""
        return {
            "trunk_id": (0 < self.trunk_id <= 65535, "an id in 1..65535 (0 is background)"),
            "ignored_ids": (all(0 < i <= 65535 for i in self.ignored_ids), "ids in 1..65535"),
            "kind": (self.kind in MASK_KINDS, _one_of(MASK_KINDS)),
        }


@dataclass(frozen=True)
class SegmenterConfig(OnnxSegmenterConfig):
    """Which segmenter finds branches when no mask is given, and the settings of each.

    `model`: 'learned' (the default: the shipped BranchNet network, `[segmenter.learned]`), 'learned:BUNDLE' (a
    model bundle fine-tuned on your labels, `train-segmenter --coco`; `[segmenter.learned]`'s other settings),
    'structure' (built in, 3D structure), 'geometric' (the older built-in one) or 'onnx:FILE' (your ONNX model,
    YOLOv8-seg or per-pixel logits). Your model's settings are the other `[segmenter]` keys
    (`OnnxSegmenterConfig`: `branch_classes` / `trunk_classes`, the model's class ids for branch and
    trunk; `score_threshold`, …); the built-in segmenters' are
    the sub-tables `[segmenter.learned]` (`LearnedSegmenterConfig`), `[segmenter.structure]`
    (`StructureSegmenterConfig`) and `[segmenter.geometric]` (`GeometricSegmenterConfig`).
    """

    section = "segmenter"
    error = ConfigError

    model: str = DEFAULT_SEGMENTER
    structure: StructureSegmenterConfig = field(default_factory=StructureSegmenterConfig)
    geometric: GeometricSegmenterConfig = field(default_factory=GeometricSegmenterConfig)
    learned: LearnedSegmenterConfig = field(default_factory=LearnedSegmenterConfig)

    def checks(self) -> Checks:
        """The model's settings and the model's name (its file is checked when it is loaded)."""
        try:
            named = bool(check_segmenter_name(self.model))
        except ValueError:
            named = False
        return {**super().checks(), "model": (named, SEGMENTER_NAMES)}

    def build(self, name: str | None = None) -> Segmenter:
        """The segmenter `name` names ('structure', 'geometric', 'onnx:FILE'; default `model`) with
        its settings from this section; `OnnxSegmenterError` for a model that cannot be loaded."""
        return make_segmenter(name or self.model, self.geometric, self, self.structure, self.learned)


@dataclass(frozen=True)
class Config:
    """The whole configuration, one dataclass per TOML section."""

    camera: CameraConfig = field(default_factory=CameraConfig)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    roi: RoiConfig = field(default_factory=RoiConfig)
    cutpoints: CutPointConfig = field(default_factory=CutPointConfig)
    branch_tracking: TrackerConfig = field(default_factory=TrackerConfig)
    masks: MaskConfig = field(default_factory=MaskConfig)
    segmenter: SegmenterConfig = field(default_factory=SegmenterConfig)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    api: ApiConfig = field(default_factory=ApiConfig)
    log: LogConfig = field(default_factory=LogConfig)
    shedding: SheddingConfig = field(default_factory=SheddingConfig)


#: A command-line override: the dotted key (`stereo.max_disp`, `segmenter.structure.max_range_m`) and its value.
Override = tuple[str, Any]


def did_you_mean(word: str, known: Iterable[str]) -> str:
    """'; did you mean `port`?' for the known name nearest a mistyped `word` ('' when none is near):
    a typo on the drone is found by reading the message, not the documentation."""
    near = difflib.get_close_matches(word, list(known), n=1)
    return f"; did you mean `{near[0]}`?" if near else ""


def unknown_option(table: str, key: str, known: Iterable[str]) -> str:
    """The message for `key` that the table `[table]` does not take: what it takes, and the nearest name."""
    known = list(known)
    return f"{table}.{key}: unknown option; [{table}] takes {', '.join(known)}{did_you_mean(key, known)}"


def unknown_section(name: str, known: Iterable[str]) -> str:
    """The message for a section `[name]` the file does not take: the sections it takes, and the nearest."""
    known = list(known)
    return f"[{name}]: unknown section; the file takes {', '.join(f'[{s}]' for s in known)}{did_you_mean(name, known)}"


def _wrong_type(key: str, value: Any, expected: str) -> ConfigError:
    return ConfigError(f"{key} = {value!r}: expected {expected}")


def _coerce(key: str, value: Any, annotation: Any) -> Any:
    """Check one TOML value against a field's type; ints are accepted where floats are expected,
    a table where the field is itself a settings dataclass."""
    if isinstance(annotation, type) and dataclasses.is_dataclass(annotation):
        return _table(annotation, key, value)
    if annotation is bool:
        if not isinstance(value, bool):
            raise _wrong_type(key, value, "true or false")
        return value
    if annotation is int:
        if not isinstance(value, int) or isinstance(value, bool):
            raise _wrong_type(key, value, "an integer")
        return value
    if annotation is float:
        if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)):
            raise _wrong_type(key, value, "a finite number")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise _wrong_type(key, value, "a string")
        return value
    if typing.get_origin(annotation) is tuple and typing.get_args(annotation)[1:] == (Ellipsis,):
        if not isinstance(value, list):
            raise _wrong_type(key, value, "a list")
        item = typing.get_args(annotation)[0]
        return tuple(_coerce(f"{key}[{i}]", v, item) for i, v in enumerate(value))
    if typing.get_origin(annotation) is tuple:
        items = typing.get_args(annotation)
        if not (isinstance(value, list) and len(value) == len(items)):
            raise _wrong_type(key, value, f"a list of {len(items)} numbers")
        return tuple(_coerce(f"{key}[{i}]", v, t) for i, (v, t) in enumerate(zip(value, items)))
    raise TypeError(f"config field {key} has an unsupported type {annotation!r}")


def _table(cls: type, name: str, table: Any) -> Any:
    """Settings dataclass `cls` from the TOML table `[name]`: unknown keys refused, every value
    type-checked, then the class's own range checks; every error a `ConfigError` naming the key."""
    if not isinstance(table, dict):
        raise _wrong_type(name, table, f"a table [{name}]")
    hints = typing.get_type_hints(cls)
    known = sorted(f.name for f in dataclasses.fields(cls))
    unknown = sorted(set(table) - set(known))
    if unknown:
        raise ConfigError(unknown_option(name, unknown[0], known))
    values = {key: _coerce(f"{name}.{key}", value, hints[key]) for key, value in table.items()}
    try:
        return cls(**values)
    except ConfigError:
        raise
    except ValueError as exc:  # the range check of a section defined beside its code (CutPointConfigError, …)
        raise ConfigError(str(exc)) from None


def config_from_dict(data: dict[str, Any]) -> Config:
    """Validate a parsed TOML document into a `Config`; raises `ConfigError` naming the key."""
    sections = typing.get_type_hints(Config)
    unknown = sorted(set(data) - set(sections))
    if unknown:
        raise ConfigError(unknown_section(unknown[0], sections))
    return Config(**{name: _table(sections[name], name, table) for name, table in data.items()})


def parse_override(text: str) -> Override:
    """`SECTION.KEY=VALUE` (`--set`) → (dotted key, value): the value in TOML syntax
    (`128`, `true`, `[0, -10, 0]`, `"text"`), a bare word taken as a string (`--set stereo.backend=sgbm`)."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or "." not in key or not all(key.split(".")):
        raise ConfigError(f"--set {text!r}: expected SECTION.KEY=VALUE, e.g. --set stereo.max_disp=128")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return key, value


def with_overrides(data: dict[str, Any], overrides: Iterable[Override]) -> dict[str, Any]:
    """A copy of the TOML tree `data` with each (dotted key, value) set in it, later ones winning."""
    tree: dict[str, Any] = {name: dict(table) if isinstance(table, dict) else table for name, table in data.items()}
    for key, value in overrides:
        *tables, last = key.split(".")
        node = tree
        for depth, name in enumerate(tables):
            child = node.get(name, {})
            if not isinstance(child, dict):
                raise _wrong_type(".".join(tables[: depth + 1]), child, f"a table (--set {key}=…)")
            node[name] = node = dict(child)
        node[last] = value
    return tree


def load_config(path: str | Path | None, overrides: Iterable[Override] = ()) -> Config:
    """Read and validate a TOML configuration file (`None`: the defaults), then the command line's
    `overrides` ((dotted key, value), e.g. from `parse_override`; later ones win)."""
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
            config_from_dict(data)  # the file's own errors name the file
        except FileNotFoundError:
            raise ConfigError(f"{path}: configuration file not found") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML ({exc})") from None
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
    return config_from_dict(with_overrides(data, overrides))


def pipeline_config(cfg: Config) -> Any:
    """The `branchrange.core.pipeline.PipelineConfig` of `cfg`: its pipeline sections themselves."""
    from branchrange.core.pipeline import PipelineConfig

    return PipelineConfig(
        stereo=cfg.stereo,
        roi=cfg.roi,
        cutpoints=cfg.cutpoints,
        tracker=cfg.branch_tracking,
        masks=cfg.masks,
        segmenter=cfg.segmenter,
    )
