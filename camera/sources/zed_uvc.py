"""ZED / ZED Mini over plain USB Video Class with OpenCV: no ZED SDK needed on the companion computer.

The camera delivers one side-by-side image (left | right) per frame in one of four modes. The
halves are split here; rectification needs the factory calibration (`SN<serial>.conf`) at the
matching resolution. When reads fail (cable pulled, USB reset) the source releases the device,
reports `is_lost`, and reopens it with exponential backoff until it answers again.

Hardware status: written against OpenCV's V4L2/UVC behaviour and tested with a fake capture
that replays files (tests/test_camera_sources.py); it has not been run against a real ZED here.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2

from camera.calibration import FrameSizeError, StereoCalibration
from camera.load import load_calibration
from camera.sources.frame import (
    Backoff,
    CorruptFrameError,
    SourceBase,
    SourceConfigError,
    SourceDisconnected,
    SourceUnavailable,
    StereoFrame,
)
from camera.sources.image_files import split_side_by_side


@dataclass(frozen=True)
class ZedMode:
    """One UVC mode: side-by-side frame size (both eyes), the calibration file's resolution name, frame rates."""

    width: int
    height: int
    resolution: str
    fps: tuple[int, ...]


#: The ZED's UVC modes (side-by-side sizes).
ZED_MODES: dict[str, ZedMode] = {
    "HD2K": ZedMode(4416, 1242, "2K", (15,)),
    "HD1080": ZedMode(3840, 1080, "FHD", (30, 15)),
    "HD720": ZedMode(2560, 720, "HD", (60, 30, 15)),
    "VGA": ZedMode(1344, 376, "VGA", (100, 60, 30, 15)),
}

#: Makes a capture for a device index or path; cv2.VideoCapture, or a fake in tests.
CaptureFactory = Callable[[int | str], Any]


def open_uvc_capture(device: int | str) -> cv2.VideoCapture:
    """OpenCV's capture of a UVC device by index or /dev/video* path."""
    return cv2.VideoCapture(device)


def zed_mode(name: str) -> ZedMode:
    """The mode for a name (HD2K, HD1080, HD720, VGA; any case)."""
    key = name.strip().upper()
    if key not in ZED_MODES:
        raise SourceConfigError(f"ZED mode is {name!r}; expected one of {', '.join(ZED_MODES)}")
    return ZED_MODES[key]


class ZedUvcSource(SourceBase):
    """Stereo frames from a ZED / ZED Mini opened as a UVC webcam.

    `device`: index (0) or path ("/dev/video0"). `mode`: HD2K, HD1080, HD720 or VGA; `fps` one of
    the mode's rates (default 30, or the mode's only one). `calibration`: a StereoCalibration or a
    calibration file, e.g. the camera's `SN<serial>.conf` (read at the mode's resolution). `reconnect=False` raises
    SourceDisconnected instead of reopening. `capture_factory`, `sleep` and `clock` are injection
    points for tests (a fake capture, no real waiting, a fake clock).
    The constructor raises SourceUnavailable when the device cannot be opened at all, and
    FrameSizeError when the calibration is for another image size than one eye of the mode.
    """

    def __init__(
        self,
        device: int | str = 0,
        mode: str = "HD720",
        fps: int | None = None,
        *,
        calibration: StereoCalibration | str | Path | None = None,
        reconnect: bool = True,
        backoff: Backoff | None = None,
        capture_factory: CaptureFactory = open_uvc_capture,
        sleep: Callable[[float], Any] | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.device = device
        self.mode = zed_mode(mode)
        self.mode_name = mode.strip().upper()
        self.fps = fps if fps is not None else (30 if 30 in self.mode.fps else self.mode.fps[0])
        if self.fps not in self.mode.fps:
            raise SourceConfigError(
                f"fps {self.fps} is not offered in mode {self.mode_name}; expected one of "
                f"{', '.join(map(str, self.mode.fps))}"
            )
        if isinstance(calibration, (str, Path)):
            calibration = load_calibration(calibration, self.mode.resolution)
        eye_size = (self.mode.width // 2, self.mode.height)
        if calibration is not None and calibration.image_size != eye_size:
            raise FrameSizeError(
                calibration.source,
                "image_size",
                f"is {calibration.width}×{calibration.height} px",
                f"{eye_size[0]}×{eye_size[1]} px, one eye in mode {self.mode_name}",
            )
        self.calibration = calibration
        self.reconnect = reconnect
        self.backoff = backoff or Backoff()
        self._factory = capture_factory
        self._stop = threading.Event()
        self._sleep = sleep or self._stop.wait
        self._clock = clock
        self._io_lock = threading.Lock()
        self._lost = False
        self._index = 0
        self.reconnects = 0
        self._capture = self._open()
        if self._capture is None:
            raise SourceUnavailable(
                f"ZED camera {device!r} cannot be opened in mode {self.mode_name} "
                f"({self.mode.width}×{self.mode.height} @ {self.fps} fps); is it plugged in, "
                "and is the device index or /dev/video path right?"
            )

    @property
    def is_lost(self) -> bool:
        return self._lost

    def _open(self) -> Any | None:
        """A capture set to the mode, or None when the device does not open or refuses the mode."""
        capture = self._factory(self.device)
        if not capture.isOpened():
            capture.release()
            return None
        capture.set(cv2.CAP_PROP_FRAME_WIDTH, self.mode.width)
        capture.set(cv2.CAP_PROP_FRAME_HEIGHT, self.mode.height)
        capture.set(cv2.CAP_PROP_FPS, self.fps)
        got = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        if got != (self.mode.width, self.mode.height):
            capture.release()
            raise SourceConfigError(
                f"ZED camera {self.device!r} delivers {got[0]}×{got[1]} instead of mode "
                f"{self.mode_name} ({self.mode.width}×{self.mode.height}); is it a ZED?"
            )
        return capture

    def _lose(self) -> None:
        """Release a capture that stopped delivering and mark the camera lost."""
        if self._capture is not None:
            self._capture.release()
            self._capture = None
        self._lost = True
        if not self.reconnect:
            raise SourceDisconnected(f"ZED camera {self.device!r} stopped delivering frames")

    def _reopen(self) -> None:
        """Retry opening with exponential backoff until it works or the source is closed."""
        while self._capture is None and not self._stop.is_set():
            self._sleep(self.backoff.next_delay())
            if self._stop.is_set():
                return
            self._capture = self._open()
        if self._capture is not None:
            self.reconnects += 1

    def __next__(self) -> StereoFrame:
        while True:
            with self._io_lock:
                if self._stop.is_set():
                    raise StopIteration
                if self._capture is None:
                    self._reopen()
                    continue
                ok, bgr = self._capture.read()
                timestamp = self._clock()
                if not ok or bgr is None:
                    self._lose()
                    continue
            self._lost = False
            self.backoff.reset()
            if bgr.shape[:2] != (self.mode.height, self.mode.width):
                raise CorruptFrameError(
                    f"ZED camera {self.device!r} gave a {bgr.shape[1]}×{bgr.shape[0]} frame; "
                    f"expected {self.mode.width}×{self.mode.height} ({self.mode_name})"
                )
            left, right = split_side_by_side(bgr)
            frame = StereoFrame(left, right, timestamp, self._index)
            self._index += 1
            return frame

    def close(self) -> None:
        """Stop (a reconnection wait returns at once) and release the device."""
        self._stop.set()
        with self._io_lock:
            if self._capture is not None:
                self._capture.release()
                self._capture = None
