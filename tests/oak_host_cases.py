"""OakSource on depthai's real host-side machinery: a host-only pipeline, the Sync node, real ImgFrames.

Run by tests/test_camera_oak.py in a child process with a hard time limit (see there why).

No OAK device exists here, and depthai cannot create Camera nodes without one, so two host nodes
that send frames (made from arrays, as the cameras would) stand in for the left and right cameras.
"""

from __future__ import annotations

import datetime
import threading
import time
from pathlib import Path

import numpy as np
import pytest

dai = pytest.importorskip("depthai", reason="depthai is not installed; the OAK source needs it")

from camera import from_depthai_json  # noqa: E402
from camera.sources import SourceConfigError, SourceDisconnected  # noqa: E402
from camera.sources.oak import OakConfig, OakSession, OakSource, add_stereo_cameras, image_to_rgb  # noqa: E402

WIDTH, HEIGHT = 48, 32
PERIOD_MS = 30


class ArrayCamera(dai.node.ThreadedHostNode):
    """A host node that sends a fixed list of ImgFrames at once, then goes quiet (a camera that stopped).

    depthai's Pipeline.stop() holds the GIL while it joins host-node threads, so a Python host node
    must have returned before the source is closed: `finished` tells the test when it has.
    """

    def __init__(self) -> None:
        super().__init__()
        self.out = self.createOutput()
        self.frames: list = []
        self.finished = threading.Event()

    def run(self) -> None:
        for frame in self.frames:
            self.out.send(frame)
        self.finished.set()


def gray_frame(value: int, at_ms: float) -> dai.ImgFrame:
    frame = dai.ImgFrame()
    image = np.full((HEIGHT, WIDTH), value, np.uint8)
    image[0, 0] = 255 - value
    frame.setCvFrame(image, dai.ImgFrame.Type.GRAY8)
    frame.setTimestamp(datetime.timedelta(milliseconds=at_ms))
    return frame


class HostSessions:
    """Opens host-only sessions; each serves `pairs` frame pairs (right frames 1 ms after left), minus `skip_right`."""

    def __init__(self, pairs: int, calibration=None, skip_right: frozenset[int] = frozenset()) -> None:
        self.pairs, self.calibration, self.skip_right = pairs, calibration, skip_right
        self.opened = 0
        self.cameras: list[ArrayCamera] = []

    def __call__(self, config: OakConfig) -> OakSession:
        pipeline = dai.Pipeline(False)
        left, right = pipeline.create(ArrayCamera), pipeline.create(ArrayCamera)
        base = 1000.0 * (self.opened + 1)
        left.frames = [gray_frame(10 + i, base + i * PERIOD_MS) for i in range(self.pairs)]
        right.frames = [
            gray_frame(100 + i, base + i * PERIOD_MS + 1) for i in range(self.pairs) if i not in self.skip_right
        ]
        self.opened += 1
        self.cameras += [left, right]
        return OakSession(pipeline, left.out, right.out, self.calibration)

    def close(self, source: OakSource) -> None:
        """Close `source` once every stand-in camera has sent its frames (see ArrayCamera)."""
        for camera in self.cameras:
            assert camera.finished.wait(10.0)
        time.sleep(0.2)  # let the host-node threads return before stop() joins them holding the GIL
        source.close()


@pytest.fixture(scope="module")
def oak_calibration(tmp_path_factory: pytest.TempPathFactory):
    handler = dai.CalibrationHandler()
    socket = dai.CameraBoardSocket
    handler.setCameraIntrinsics(socket.CAM_B, [[800.0, 0, 640], [0, 800.0, 400], [0, 0, 1]], 1280, 800)
    handler.setCameraIntrinsics(socket.CAM_C, [[802.0, 0, 636], [0, 802.0, 404], [0, 0, 1]], 1280, 800)
    handler.setCameraExtrinsics(socket.CAM_B, socket.CAM_C, np.eye(3).tolist(), [-7.5, 0, 0], [-7.5, 0, 0])
    path = tmp_path_factory.mktemp("oak") / "calib.json"
    handler.eepromToJsonFile(str(path))
    return from_depthai_json(path, size=(WIDTH, HEIGHT))


def test_oak_source_pairs_frames_by_timestamp_and_converts_to_rgb(oak_calibration) -> None:
    sessions = HostSessions(5, oak_calibration, skip_right=frozenset({2}))
    config = OakConfig(size=(WIDTH, HEIGHT), sync_threshold_ms=5, frame_timeout_s=1.0)
    source = OakSource(config, open_session=sessions, reconnect=False)
    got = [next(source) for _ in range(4)]
    assert source.calibration is oak_calibration
    sessions.close(source)
    lefts = [int(f.left[1, 1, 0]) for f in got]
    rights = [int(f.right[1, 1, 0]) for f in got]
    assert lefts == [10, 11, 13, 14] and rights == [100, 101, 103, 104]  # left 12 had no partner: dropped
    assert [f.index for f in got] == [0, 1, 2, 3]
    assert [f.timestamp_ns for f in got] == [int((1000 + i * PERIOD_MS) * 1e6) for i in (0, 1, 3, 4)]
    frame = got[0]
    assert frame.left.shape == (HEIGHT, WIDTH, 3) and frame.left.dtype == np.uint8
    assert np.all(frame.left[0, 0] == 245) and np.all(frame.left[1, 1] == 10)  # GRAY8 replicated to RGB


def test_oak_source_reports_lost_and_reopens_with_backoff() -> None:
    sessions = HostSessions(2)
    states: list[bool] = []
    source: OakSource

    def sleep(seconds: float) -> None:
        states.append(source.is_lost)

    source = OakSource(OakConfig(frame_timeout_s=0.4), open_session=sessions, sleep=sleep)
    got = [next(source) for _ in range(4)]
    sessions.close(source)
    assert [int(f.left[1, 1, 0]) for f in got] == [10, 11, 10, 11]  # the second session's stream
    assert got[2].timestamp_ns > got[1].timestamp_ns and [f.index for f in got] == [0, 1, 2, 3]
    assert sessions.opened == 2 and source.reconnects == 1
    assert states == [True] and not source.is_lost


def test_oak_source_without_reconnect_raises_disconnected() -> None:
    sessions = HostSessions(1)
    source = OakSource(OakConfig(frame_timeout_s=0.3), open_session=sessions, reconnect=False)
    next(source)
    with pytest.raises(SourceDisconnected, match="no frame pair for 0.3 s"):
        next(source)
    assert source.is_lost
    sessions.close(source)


def test_image_to_rgb_keeps_rgb_and_swaps_bgr() -> None:
    image = np.zeros((4, 6, 3), np.uint8)
    image[..., 0] = 200  # red in RGB
    rgb, bgr = dai.ImgFrame(), dai.ImgFrame()
    rgb.setFrame(image)
    rgb.setType(dai.ImgFrame.Type.RGB888i)
    rgb.setWidth(6)
    rgb.setHeight(4)
    bgr.setCvFrame(image[..., ::-1].copy(), dai.ImgFrame.Type.BGR888i)
    assert np.array_equal(image_to_rgb(rgb), image)
    assert np.array_equal(image_to_rgb(bgr), image)


def test_camera_nodes_need_a_device_and_config_is_checked() -> None:
    with pytest.raises(RuntimeError, match="host only"):
        add_stereo_cameras(dai.Pipeline(False), OakConfig())
    with pytest.raises(SourceConfigError, match="left_socket"):
        OakConfig(left_socket="CAM_Z")
    with pytest.raises(SourceConfigError, match="size"):
        OakConfig(size=(0, 400))


def test_device_calibration_dict_matches_the_json_file(oak_calibration, tmp_path: Path) -> None:
    from camera.depthai_json import calibration_from_depthai_dict

    handler = dai.CalibrationHandler(oak_calibration.source)
    from_dict = calibration_from_depthai_dict(handler.eepromToJson(), "eeprom", "CAM_B", "CAM_C", (WIDTH, HEIGHT))
    assert from_dict == oak_calibration
