"""Luxonis OAK cameras over depthai v3: two Camera nodes, host-side pairing by timestamp, device calibration.

Pipeline: `dai.node.Camera` built on the left and right sockets, each asked for one output at the
chosen size and fps (`requestOutput`: GRAY8 for mono sensors, RGB888i for colour ones), both
linked into a `dai.node.Sync` node run on the host that groups frames whose timestamps lie within
`sync_threshold_ms`, read from one output queue. Calibration comes from the device EEPROM
(`readCalibration().eepromToJson()`), scaled to the output size by camera.depthai_json.

Hardware status: nothing here has run on an OAK device. The tests run the real depthai pipeline
machinery on the host (a host-only `dai.Pipeline(False)`, the real Sync node, real ImgFrame and
MessageGroup messages) with file-fed host nodes in place of the two Camera nodes, which depthai
cannot create without a device. The device half is split so that what can be checked is:
`camera_requests` (sockets, size, frame type, resize mode, fps) is tested, and `add_stereo_cameras`
is run against a recording stand-in pipeline and against depthai's own signatures; building real
Camera nodes, `readCalibration()` and frames from real sensors have not run.
"""

from __future__ import annotations

import datetime
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import depthai as dai
import numpy as np

from camera.calibration import StereoCalibration
from camera.depthai_json import calibrated_size, calibration_from_depthai_dict, socket_number
from camera.sources.frame import (
    Backoff,
    CorruptFrameError,
    SourceBase,
    SourceConfigError,
    SourceDisconnected,
    SourceUnavailable,
    StereoFrame,
)


@dataclass(frozen=True)
class OakConfig:
    """What to ask an OAK for: sockets (names or numbers), output size (w, h), fps, colour or mono, pairing.

    `size` must be at least as wide, relative to its height, as the sensor's calibration size (e.g.
    640×400 or 1280×720 for a 1280×800 mono pair); narrower sizes are refused when the device opens
    (see `check_output_aspect`).
    """

    left_socket: str | int = "CAM_B"
    right_socket: str | int = "CAM_C"
    size: tuple[int, int] = (640, 400)
    fps: float = 30.0
    color: bool = False
    sync_threshold_ms: float = 10.0
    queue_size: int = 4
    frame_timeout_s: float = 2.0

    def __post_init__(self) -> None:
        for key in ("left_socket", "right_socket"):
            try:
                socket_number(getattr(self, key))
            except ValueError as error:
                raise SourceConfigError(f"OakConfig.{key}: {error}") from None
        if len(self.size) != 2 or min(self.size) <= 0:
            raise SourceConfigError(f"OakConfig.size is {self.size}; expected a positive (width, height)")
        if self.fps <= 0 or self.sync_threshold_ms <= 0 or self.frame_timeout_s <= 0 or self.queue_size < 1:
            raise SourceConfigError(
                f"OakConfig needs positive fps, sync_threshold_ms, frame_timeout_s and queue_size ≥ 1; got {self}"
            )


@dataclass
class OakSession:
    """A built, not yet started pipeline: its left and right frame outputs and the device's calibration."""

    pipeline: dai.Pipeline
    left: Any
    right: Any
    calibration: StereoCalibration | None


@dataclass(frozen=True)
class CameraRequest:
    """What one Camera node is built with and asked for: socket, output size (w, h) px, type, resize, fps."""

    socket: dai.CameraBoardSocket
    size: tuple[int, int]
    frame_type: dai.ImgFrame.Type
    resize_mode: dai.ImgResizeMode
    fps: float


def camera_requests(config: OakConfig) -> tuple[CameraRequest, CameraRequest]:
    """The left and right Camera node requests for a config (no device needed: this is what tests check).

    Mono sensors give GRAY8, colour ones RGB888i; CROP keeps the aspect ratio (no warping), which
    the calibration scaling of camera.depthai_json assumes (see `check_output_aspect`).
    """
    frame_type = dai.ImgFrame.Type.RGB888i if config.color else dai.ImgFrame.Type.GRAY8
    left, right = (
        CameraRequest(
            dai.CameraBoardSocket(socket_number(socket)),
            (int(config.size[0]), int(config.size[1])),
            frame_type,
            dai.ImgResizeMode.CROP,
            float(config.fps),
        )
        for socket in (config.left_socket, config.right_socket)
    )
    return left, right


def add_stereo_cameras(pipeline: dai.Pipeline, config: OakConfig) -> tuple[Any, Any]:
    """Camera nodes on both sockets, each with one output as `camera_requests` says; (left, right) outputs.

    Needs a pipeline bound to a device: depthai refuses device nodes in a host-only pipeline.
    """
    outputs = []
    for request in camera_requests(config):
        camera = pipeline.create(dai.node.Camera).build(request.socket)
        # enableUndistortion=False: the host Rectifier undistorts with the EEPROM's coefficients; frames
        # undistorted on the device as well would be corrected twice.
        outputs.append(
            camera.requestOutput(
                request.size,
                request.frame_type,
                resizeMode=request.resize_mode,
                fps=request.fps,
                enableUndistortion=False,
            )
        )
    return outputs[0], outputs[1]


def check_output_aspect(calibrated_size: tuple[int, int], config: OakConfig) -> None:
    """Refuse an output size narrower than the sensor's calibrated aspect ratio (SourceConfigError).

    Why: for such sizes the Camera node's CROP trims the sides and scales by the height, while
    depthai's `getCameraIntrinsics` (and camera.depthai_json, which matches it) scale by the width,
    so the focal length would be off by the ratio of the two aspect ratios. For outputs as wide as
    the sensor or wider, both crop top and bottom and agree.
    """
    width, height = config.size
    calib_width, calib_height = calibrated_size
    if width * calib_height < calib_width * height * (1 - 1e-3):
        raise SourceConfigError(
            f"OakConfig.size is {width}×{height}, narrower than the {calib_width}×{calib_height} the sensor on "
            f"{config.left_socket} was calibrated at; expected an aspect ratio ≥ {calib_width / calib_height:.3f} "
            f"(e.g. {width}×{int(width * calib_height / calib_width)})"
        )


def add_pair_sync(pipeline: dai.Pipeline, left: Any, right: Any, config: OakConfig) -> Any:
    """A host-side Sync node pairing `left` and `right` frames; returns the queue of paired MessageGroups."""
    sync = pipeline.create(dai.node.Sync)
    sync.setRunOnHost(True)
    sync.setSyncThreshold(datetime.timedelta(milliseconds=config.sync_threshold_ms))
    left.link(sync.inputs["left"])
    right.link(sync.inputs["right"])
    return sync.out.createOutputQueue(maxSize=config.queue_size, blocking=False)


def open_oak_device(config: OakConfig) -> OakSession:
    """Connect to the first OAK found, build both cameras and read its calibration for the chosen sockets."""
    try:
        pipeline = dai.Pipeline()
    except RuntimeError as error:
        raise SourceUnavailable(f"no OAK device could be opened: {error}") from None
    eeprom = pipeline.getDefaultDevice().readCalibration().eepromToJson()
    check_output_aspect(calibrated_size(eeprom, config.left_socket, "OAK device EEPROM"), config)
    left, right = add_stereo_cameras(pipeline, config)
    calibration = calibration_from_depthai_dict(
        eeprom, "OAK device EEPROM", config.left_socket, config.right_socket, (int(config.size[0]), int(config.size[1]))
    )
    return OakSession(pipeline, left, right, calibration)


def image_to_rgb(frame: dai.ImgFrame) -> np.ndarray:
    """An H×W×3 uint8 RGB array from a depthai ImgFrame (GRAY8 is replicated, other types go through BGR)."""
    kind = frame.getType()
    if kind == dai.ImgFrame.Type.RGB888i:
        return np.ascontiguousarray(frame.getFrame())
    if kind in (dai.ImgFrame.Type.GRAY8, dai.ImgFrame.Type.RAW8):
        return cv2.cvtColor(frame.getFrame(), cv2.COLOR_GRAY2RGB)
    bgr = frame.getCvFrame()
    if bgr is None or bgr.ndim != 3:
        raise CorruptFrameError(f"OAK frame of type {kind} could not be converted to colour")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def timestamp_ns(frame: dai.ImgFrame) -> int:
    """The frame's capture time on the host's monotonic clock, nanoseconds (depthai gives microseconds)."""
    return (frame.getTimestamp() // datetime.timedelta(microseconds=1)) * 1000


class OakSource(SourceBase):
    """Stereo pairs from an OAK camera (see the module docstring for the pipeline and what was tested).

    `config`: sockets, size, fps, colour, pairing threshold and the time without frames after which
    the camera counts as lost (`is_lost`); it is then reopened with exponential backoff, or
    SourceDisconnected is raised when `reconnect=False`. `calibration` overrides the device's.
    `open_session` builds the pipeline (default: the first OAK device); tests give a host pipeline.
    """

    def __init__(
        self,
        config: OakConfig | None = None,
        *,
        calibration: StereoCalibration | None = None,
        open_session: Callable[[OakConfig], OakSession] = open_oak_device,
        reconnect: bool = True,
        backoff: Backoff | None = None,
        sleep: Callable[[float], Any] | None = None,
    ) -> None:
        self.config = config or OakConfig()
        self.reconnect = reconnect
        self.backoff = backoff or Backoff()
        self._open_session = open_session
        self._stop = threading.Event()
        self._sleep = sleep or self._stop.wait
        self._lost = False
        self._index = 0
        self.reconnects = 0
        self._pipeline: dai.Pipeline | None = None
        self._queue: Any = None
        session = self._start()
        self.calibration = calibration if calibration is not None else session.calibration

    @property
    def is_lost(self) -> bool:
        return self._lost

    def _start(self) -> OakSession:
        session = self._open_session(self.config)
        self._queue = add_pair_sync(session.pipeline, session.left, session.right, self.config)
        session.pipeline.start()
        self._pipeline = session.pipeline
        return session

    def _stop_pipeline(self) -> None:
        if self._pipeline is not None:
            self._pipeline.stop()
            self._pipeline = None
            self._queue = None

    def _next_group(self) -> Any | None:
        """The next paired MessageGroup, or None when none came within the frame timeout or the queue closed."""
        queue = self._queue
        if queue is None:
            return None
        try:
            return queue.get(datetime.timedelta(seconds=self.config.frame_timeout_s))
        except RuntimeError:  # dai.MessageQueue.QueueException: the pipeline or the device went away
            return None

    def __next__(self) -> StereoFrame:
        while True:
            if self._stop.is_set():
                raise StopIteration
            if self._pipeline is None:
                self._sleep(self.backoff.next_delay())
                if not self._stop.is_set():
                    try:
                        self._start()
                        self.reconnects += 1
                    except (RuntimeError, SourceUnavailable):
                        pass
                continue
            group = self._next_group()
            if group is None:
                if self._stop.is_set():
                    raise StopIteration
                self._stop_pipeline()
                self._lost = True
                if not self.reconnect:
                    raise SourceDisconnected(
                        f"OAK sockets {self.config.left_socket}/{self.config.right_socket}: no "
                        f"frame pair for {self.config.frame_timeout_s} s"
                    )
                continue
            self._lost = False
            self.backoff.reset()
            left, right = group["left"], group["right"]
            frame = StereoFrame(image_to_rgb(left), image_to_rgb(right), timestamp_ns(left), self._index)
            self._index += 1
            return frame

    def close(self) -> None:
        """Stop the pipeline and release the device."""
        self._stop.set()
        self._stop_pipeline()
