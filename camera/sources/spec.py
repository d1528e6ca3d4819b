"""`open_source(spec)`: a frame source from a short text spec, as the command line and config files give it.

Specs: `zed:0`, `zed:0:HD720`, `zed:/dev/video0`, `zed:/dev/video0:VGA` (device index or path, then
an optional mode), `oak`, `oak:640x400`, `oak:1280x800@60` (output size and fps), `replay:PATH`
(a recording directory, a folder of pairs `left/` + `right/`, or a side-by-side video file),
`rosbag:PATH[?left=TOPIC&…]` (a ROS 2 bag, see camera.sources.rosbag). Both replays take the options
`start_at=TIME`, `start_signal=file:PATH|udp:HOST:PORT` (repeatable; camera.sources.clock_sync),
`ignore_masks=true` and `max_late_ms=MS` (camera.sources.replay.ReplaySource), e.g.
`replay:out/flight?start_signal=udp:127.0.0.1:9500&start_at=2026-11-28T18:10:00Z`.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TypeVar

from camera.calibration import CalibrationError, StereoCalibration
from camera.load import detect_format, load_calibration
from camera.sources.clock_sync import ClockSync
from camera.sources.frame import SourceBase, SourceConfigError, SourceError
from camera.sources.latest import LatestFrameSource
from camera.sources.replay import ReplaySource
from camera.sources.spec_options import REPLAY_KEYS, replay_options, split_spec
from camera.sources.zed_uvc import ZED_MODES, ZedUvcSource
from camera.zed_conf import ZED_RESOLUTIONS, resolution_for_size

_OAK_OPTIONS = re.compile(r"^(\d+)x(\d+)(?:@(\d+(?:\.\d+)?))?$")
T = TypeVar("T")
_MODE_LIKE = re.compile(r"^[A-Za-z0-9]*[A-Za-z][A-Za-z0-9]*$")  # a bare word with a letter, no path characters


def parse_zed_spec(rest: str) -> tuple[int | str, str]:
    """(device, mode) from what follows `zed:`: an index or path, then an optional `:MODE`.

    A (trailing `:`) word that looks like a mode name but is none raises SourceConfigError; other
    colons belong to the path (udev's /dev/v4l/by-path names contain some).
    """
    device_text, mode = rest, "HD720"
    head, sep, tail = rest.rpartition(":")
    if sep and tail.upper() in ZED_MODES:
        device_text, mode = head, tail.upper()
    elif rest.upper() in ZED_MODES:
        device_text, mode = "0", rest.upper()
    elif _MODE_LIKE.match(tail):
        raise SourceConfigError(
            f"source spec 'zed:{rest}': mode {tail!r} is unknown; expected one of "
            f"{', '.join(ZED_MODES)} (after a device index or /dev/video path)"
        )
    device_text = device_text or "0"
    device: int | str = int(device_text) if device_text.isdigit() else device_text
    return device, mode


def open_source(
    spec: str,
    *,
    calibration: StereoCalibration | str | Path | None = None,
    latest: bool = False,
    pace: str = "recorded",
    loop: bool = False,
    start: int = 0,
    fps: float | None = None,
    ignore_masks: bool = False,
    clock_sync: ClockSync | None = None,
    max_late_ms: float | None = None,
) -> SourceBase:
    """Open the source a spec names (see the module docstring).

    `calibration`: a StereoCalibration or a calibration file overriding what the source knows; a
    file is read for the source's frame size (a ZED conf at the ZED mode's or the recording's
    resolution, a depthai JSON scaled to the OAK output or recording size). `latest=True` wraps the source in
    LatestFrameSource (a slow consumer then always gets the newest frame). `pace`, `loop`, `start`,
    `ignore_masks`, `clock_sync` and `max_late_ms` apply to replays (as their spec options do; a clock
    sync or late limit given both ways is refused), `fps` to `replay:` (a folder of pairs' frame rate, or a
    video's override).
    """
    kind, _, rest = spec.strip().partition(":")
    kind = kind.lower()
    if kind == "zed":
        device, mode = parse_zed_spec(rest)
        source: SourceBase = ZedUvcSource(device, mode, calibration=calibration)
    elif kind == "oak":
        from camera.sources.oak import OakConfig, OakSource  # depthai is imported only when an OAK is used

        match = _OAK_OPTIONS.match(rest) if rest else None
        if rest and match is None:
            raise SourceConfigError(f"source spec {spec!r}: expected oak, oak:WIDTHxHEIGHT or oak:WIDTHxHEIGHT@FPS")
        config = (
            OakConfig()
            if match is None
            else OakConfig(size=(int(match[1]), int(match[2])), fps=float(match[3]) if match[3] else OakConfig.fps)
        )
        source = OakSource(config, calibration=_loaded(calibration, config.size))
    elif kind == "replay":
        path, options = split_spec(spec, rest, REPLAY_KEYS)
        if not path:
            raise SourceConfigError(f"source spec {spec!r}: expected replay:PATH[?OPTION=VALUE&…]")
        asked = replay_options(spec, options)
        source = _calibrated(
            ReplaySource(
                path,
                pace=pace,
                loop=loop,
                start=start,
                fps=fps,
                ignore_masks=ignore_masks or asked.ignore_masks,
                clock_sync=_given_once(spec, "start_at/start_signal", asked.clock_sync, clock_sync),
                max_late_ms=_given_once(spec, "max_late_ms", asked.max_late_ms, max_late_ms),
            ),
            calibration,
        )
    elif kind == "rosbag":
        from camera.sources.rosbag import RosbagSource, parse_rosbag_spec  # rosbags is imported only for bags

        bag, topics, tolerance_ms, options = parse_rosbag_spec(rest)
        asked = replay_options(spec, options)  # a bag has no masks to ignore
        source = _calibrated(
            RosbagSource(
                bag,
                topics=topics,
                tolerance_ms=tolerance_ms,
                use_camera_info=calibration is None,
                pace=pace,
                loop=loop,
                start=start,
                clock_sync=_given_once(spec, "start_at/start_signal", asked.clock_sync, clock_sync),
                max_late_ms=_given_once(spec, "max_late_ms", asked.max_late_ms, max_late_ms),
            ),
            calibration,
        )
    else:
        raise SourceConfigError(
            f"source spec {spec!r}: expected zed:DEVICE[:MODE], oak[:WxH[@FPS]], replay:PATH or rosbag:PATH"
        )
    return LatestFrameSource(source) if latest else source


def _given_once(spec: str, name: str, from_spec: T | None, given: T | None) -> T | None:
    """A replay option from the spec or from the caller; both at once would leave one of them silently unused."""
    if from_spec is not None and given is not None:
        raise SourceConfigError(f"source spec {spec!r}: {name} given in the spec and as an option; give it once")
    return given if from_spec is None else from_spec


def _calibrated(source: ReplaySource, calibration: StereoCalibration | str | Path | None) -> ReplaySource:
    """The replay `source` with `calibration` (an object, or a file read for the source's frame size) in place
    of its own when given; the source is closed when the calibration cannot be used."""
    if calibration is not None:
        try:
            source.calibration = _loaded(calibration, source.frame_size)
        except (CalibrationError, SourceError):
            source.close()
            raise
    return source


def _loaded(calibration: StereoCalibration | str | Path | None, size: tuple[int, int]) -> StereoCalibration | None:
    """A calibration given as an object or a file, for frames of `size` (w, h) px.

    A ZED conf is read at the resolution of that size, a depthai JSON is scaled to it, and an
    OpenCV file without an image size takes it.
    """
    if calibration is None or isinstance(calibration, StereoCalibration):
        return calibration
    resolution = resolution_for_size(size)
    if resolution is None and detect_format(calibration) == "zed":
        sizes = ", ".join(f"{w}×{h}" for w, h in ZED_RESOLUTIONS.values())
        raise CalibrationError(
            calibration,
            "resolution",
            f"the frames are {size[0]}×{size[1]} px per view, which is no ZED resolution",
            f"frames of {sizes} px per view",
        )
    return load_calibration(calibration, resolution, size=size)
