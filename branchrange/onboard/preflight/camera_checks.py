"""The camera checks: the camera opens and frames arrive at its configured rate; the calibration is this camera's.

The source is opened as the daemon opens it (`camera.source`, `camera.calibration`, frames released at
their recorded times for a `replay:`), and `SAMPLED_FRAMES` frames are read; the rate is measured
between the first and the last arrival. A camera that stops for `camera.stall_timeout_s` fails, as the
daemon's watchdog would declare it lost. The frames read are kept: the latency check runs them through
the pipeline.

"This camera's calibration" is checked on what the camera tells: the calibration's image size must be
the frames' size (a calibration of another mode or camera model), and, when the operator gives the
serial on the camera's label (`--camera-serial`), the calibration file must be that camera's factory
file `SN<serial>.conf` (a ZED's calibration of a twin camera has the same size, but not the same
lens-by-lens values).
"""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from branchrange.onboard.preflight.report import CheckResult
from camera.calibration import CalibrationError, StereoCalibration
from camera.sources import SourceError, StereoFrame, open_source

if TYPE_CHECKING:
    from branchrange.config.sections import CameraConfig

SAMPLED_FRAMES = 4
#: The measured frame rate must reach this share of the configured one (USB 2 ports and overloaded
#: hubs halve it; a busy CPU decoding a replay loses a little).
RATE_TOLERANCE = 0.8
CAMERA, CALIBRATION = "camera", "calibration"
SERIAL_IN_FILE_NAME = re.compile(r"SN(\d+)", re.IGNORECASE)


@dataclass(frozen=True)
class CameraSample:
    """What the camera gave: `frames` read in order, and the `calibration` in effect for them (None: none)."""

    frames: list[StereoFrame]
    calibration: StereoCalibration | None


def configured_fps(source: Any) -> float | None:
    """The frame rate the source was set up for (a ZED's mode fps, a replay's recorded rate, an OAK's
    requested one); None when it does not say."""
    fps = getattr(source, "fps", None)
    if fps is None:
        fps = getattr(getattr(source, "config", None), "fps", None)
    return None if fps is None else float(fps)


def read_frames(source: Any, count: int, stall_timeout_s: float) -> tuple[list[tuple[StereoFrame, float]], str]:
    """Up to `count` (frame, arrival monotonic s) pairs, and why there are fewer ('' when there are not): the
    source ended, failed, or gave nothing for `stall_timeout_s` (it is read in a thread of its own, since a
    stalled camera blocks `next()`)."""
    got: list[tuple[StereoFrame, float]] = []
    problem = ["the source ended"]

    def reader() -> None:
        try:
            for frame in source:
                got.append((frame, time.monotonic()))
                if len(got) >= count:
                    problem[0] = ""
                    return
        except SourceError as exc:
            problem[0] = str(exc)

    thread = threading.Thread(target=reader, name="preflight-camera", daemon=True)
    last = time.monotonic()
    thread.start()
    seen = 0
    while thread.is_alive() and time.monotonic() - last < stall_timeout_s:
        thread.join(timeout=0.02)
        if len(got) > seen:
            seen, last = len(got), time.monotonic()
    if thread.is_alive():
        return list(got), f"no frame for camera.stall_timeout_s ({stall_timeout_s:g} s)"
    return list(got), problem[0]


def check_camera(camera: CameraConfig, camera_serial: str | None) -> tuple[list[CheckResult], CameraSample | None]:
    """The camera and calibration checks, and the frames read (None when the camera gave none)."""
    calibration_problem = None
    try:
        try:
            source = open_source(camera.source, calibration=camera.calibration or None, pace="recorded")
        except CalibrationError as exc:  # the camera may still be fine: open it alone to find out
            calibration_problem = str(exc)
            source = open_source(camera.source, pace="recorded")
    except SourceError as exc:
        fix = "plug the camera in (or fix camera.source: zed:DEVICE[:MODE], oak, replay:PATH) and run preflight again"
        return [
            CheckResult.failed(CAMERA, f"{camera.source}: {exc}", fix),
            CheckResult.skipped(CALIBRATION, "no camera to check it against"),
        ], None
    try:
        arrivals, problem = read_frames(source, SAMPLED_FRAMES, camera.stall_timeout_s)
        expected_fps = configured_fps(source)
        calibration = source.calibration
    finally:
        source.close()
    camera_result = _rate_result(camera, arrivals, problem, expected_fps)
    if not arrivals:
        return [camera_result, CheckResult.skipped(CALIBRATION, "no frame to check it against")], None
    frames = [frame for frame, _ in arrivals]
    if calibration_problem is not None:
        calibration_result = CheckResult.failed(
            CALIBRATION, calibration_problem, "set camera.calibration to this camera's calibration file"
        )
    else:
        calibration_result = _calibration_result(camera, calibration, frames[0].size, camera_serial)
    return [camera_result, calibration_result], CameraSample(frames, calibration)


def _rate_result(
    camera: CameraConfig, arrivals: list[tuple[StereoFrame, float]], problem: str, expected: float | None
) -> CheckResult:
    if problem:
        return CheckResult.failed(
            CAMERA,
            f"{camera.source}: {len(arrivals)} of {SAMPLED_FRAMES} frames, then {problem}",
            "check the camera's cable and USB port (USB 3), then run preflight again",
        )
    width, height = arrivals[0][0].size
    rate = (len(arrivals) - 1) / max(arrivals[-1][1] - arrivals[0][1], 1e-9)
    found = f"{camera.source}: {width}×{height} px frames at {rate:.1f} fps"
    if expected is None:
        return CheckResult.passed(CAMERA, found + " (the source states no rate)")
    found += f", configured {expected:g} fps"
    if rate < RATE_TOLERANCE * expected:
        return CheckResult.failed(
            CAMERA,
            found,
            "frames come too slowly: use a USB 3 port and cable, no hub, and close other camera users",
        )
    return CheckResult.passed(CAMERA, found)


def _calibration_result(
    camera: CameraConfig, calibration: StereoCalibration | None, size: tuple[int, int], camera_serial: str | None
) -> CheckResult:
    if calibration is None:
        return CheckResult.failed(
            CALIBRATION,
            f"{camera.source} brings no calibration and camera.calibration is not set",
            "set camera.calibration to this camera's calibration file (a ZED: its SN<serial>.conf)",
        )
    width, height = calibration.image_size
    if (width, height) != size:
        return CheckResult.failed(
            CALIBRATION,
            f"{calibration.source} is for {width}×{height} px, the camera gives {size[0]}×{size[1]} px",
            f"set camera.calibration to this camera's calibration for {size[0]}×{size[1]} px frames "
            "(a ZED's SN<serial>.conf is read at the source's mode)",
        )
    found = f"{calibration.source}: {width}×{height} px"
    if camera_serial is None:
        return CheckResult.passed(CALIBRATION, found + " (serial not checked: no --camera-serial)")
    match = SERIAL_IN_FILE_NAME.search(Path(camera.calibration).name) if camera.calibration else None
    if match is None or match[1] != camera_serial.strip():
        named = f"serial {match[1]}" if match else "no serial"
        return CheckResult.failed(
            CALIBRATION,
            f"{found}, but its file name names {named}, the camera's label {camera_serial}",
            f"set camera.calibration to SN{camera_serial}.conf, this camera's factory calibration",
        )
    return CheckResult.passed(CALIBRATION, f"{found}, serial {camera_serial}")
