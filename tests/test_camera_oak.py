"""OAK source: the host-pipeline cases in a child process with a time limit, and the device half's construction.

The host-pipeline cases (tests/oak_host_cases.py) run in a child process with a time limit.

depthai's Pipeline.stop() joins host-node threads while holding the GIL; the Python host nodes
that stand in for the cameras here can deadlock it if one is still returning. Real OAK cameras
are device nodes, so production code never meets this; the child process keeps a deadlock in the
test stand-ins from hanging the whole suite: it is killed and retried once.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

dai = pytest.importorskip("depthai", reason="depthai is not installed; the OAK source needs it")

from camera.sources import SourceConfigError  # noqa: E402
from camera.sources.oak import (  # noqa: E402
    CameraRequest,
    OakConfig,
    add_stereo_cameras,
    camera_requests,
    check_output_aspect,
)

CASES = Path(__file__).with_name("oak_host_cases.py")


def _run_cases() -> subprocess.CompletedProcess[str] | None:
    try:
        return subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(CASES)],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=CASES.parent.parent,
        )
    except subprocess.TimeoutExpired:
        return None


def test_oak_source_host_pipeline_cases_pass() -> None:
    result = _run_cases() or _run_cases()
    assert result is not None, "the OAK host-pipeline cases deadlocked twice (depthai stop() with host nodes)"
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert " passed" in result.stdout and "failed" not in result.stdout


# ---------------------------------------------------------------- the device half, as far as it runs without an OAK


class RecordingPipeline:
    """Stands in for a device-bound dai.Pipeline, which cannot exist here: records what is built on it."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def create(self, node_type: type) -> RecordingCamera:
        self.calls.append(("create", node_type))
        return RecordingCamera(self.calls)


class RecordingCamera:
    """A Camera node stand-in taking depthai's argument names; returns a labelled output."""

    def __init__(self, calls: list[tuple]) -> None:
        self.calls = calls

    def build(self, boardSocket: dai.CameraBoardSocket) -> RecordingCamera:  # noqa: N803 - depthai's names
        self.calls.append(("build", boardSocket))
        return self

    def requestOutput(
        self,
        size: tuple[int, int],
        type: dai.ImgFrame.Type,
        *,  # noqa: N802,A002
        resizeMode: dai.ImgResizeMode,
        fps: float,
        enableUndistortion: bool,
    ) -> str:  # noqa: N803
        self.calls.append(("requestOutput", size, type, resizeMode, fps, enableUndistortion))
        return f"output of {self.calls[-2][1].name}"


def test_camera_requests_ask_both_sockets_for_the_configured_output() -> None:
    left, right = camera_requests(OakConfig(left_socket="LEFT", right_socket=2, size=(1280, 800), fps=60))
    assert left == CameraRequest(
        dai.CameraBoardSocket.CAM_B, (1280, 800), dai.ImgFrame.Type.GRAY8, dai.ImgResizeMode.CROP, 60.0
    )
    assert right.socket == dai.CameraBoardSocket.CAM_C and right.size == (1280, 800)
    colour = camera_requests(OakConfig(left_socket="CAM_A", right_socket="CAM_D", color=True, fps=15))
    assert [r.socket for r in colour] == [dai.CameraBoardSocket.CAM_A, dai.CameraBoardSocket.CAM_D]
    assert {r.frame_type for r in colour} == {dai.ImgFrame.Type.RGB888i} and colour[0].fps == 15.0


def test_add_stereo_cameras_builds_one_camera_node_per_request() -> None:
    pipeline = RecordingPipeline()
    left, right = add_stereo_cameras(pipeline, OakConfig(size=(640, 400), fps=30))  # type: ignore[arg-type]
    assert (left, right) == ("output of CAM_B", "output of CAM_C")
    crop, gray = dai.ImgResizeMode.CROP, dai.ImgFrame.Type.GRAY8
    assert pipeline.calls == [
        ("create", dai.node.Camera),
        ("build", dai.CameraBoardSocket.CAM_B),
        ("requestOutput", (640, 400), gray, crop, 30.0, False),
        ("create", dai.node.Camera),
        ("build", dai.CameraBoardSocket.CAM_C),
        ("requestOutput", (640, 400), gray, crop, 30.0, False),
    ]


def test_installed_depthai_takes_the_arguments_add_stereo_cameras_passes() -> None:
    """The stand-ins above mirror depthai's signatures; pin those against the installed depthai."""
    build = dai.node.Camera.build.__doc__.splitlines()
    request = dai.node.Camera.requestOutput.__doc__.splitlines()
    assert any(
        line.startswith("1. build(self: depthai.node.Camera, boardSocket: depthai.CameraBoardSocket") for line in build
    )
    overload = next(line for line in request if line.startswith("1. requestOutput("))
    for parameter in (
        "size: tuple[int, int]",
        "type: Optional[depthai.ImgFrame.Type]",
        "resizeMode: depthai.ImgResizeMode",
        "fps: Optional[float]",
        "enableUndistortion: Optional[bool]",
    ):
        assert parameter in overload, (parameter, overload)


@pytest.mark.parametrize(
    "size, ok",
    [
        ((640, 400), True),
        ((1280, 800), True),
        ((1280, 720), True),
        ((640, 360), True),
        ((640, 480), False),
        ((400, 400), False),
    ],
)
def test_output_narrower_than_the_sensor_is_refused(size: tuple[int, int], ok: bool) -> None:
    config = OakConfig(size=size)
    if ok:
        check_output_aspect((1280, 800), config)
    else:
        with pytest.raises(SourceConfigError, match=rf"{size[0]}×{size[1]}, narrower than the 1280×800 .*≥ 1\.600"):
            check_output_aspect((1280, 800), config)
