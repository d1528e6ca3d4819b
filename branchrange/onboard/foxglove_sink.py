"""Per-frame results → Foxglove: a live WebSocket server and/or an MCAP file (the `foxglove-sdk` package).

`FoxgloveSink` is a frame observer, `sink(result, artifacts)`, as the daemon and the replay call
it once per processed frame with the `branchrange/v1` result and the pipeline's `FrameArtifacts`.
Each call logs, at the frame's capture time (`frame.timestamp_ns`):

| topic | Foxglove schema | what |
|---|---|---|
| /branchrange/overlay | CompressedImage (JPEG) | rectified left view with masks, cut points and target ring |
| /branchrange/disparity | CompressedImage (JPEG) | disparity, turbo colours, scale 0…max_disparity |
| /branchrange/camera_info | CameraCalibration | rectified left camera (lets the image panels project the 3D entities) |
| /branchrange/cut_points | SceneUpdate | per branch: sphere at the cut point, axis, label (id, distance, confidence) |
| /branchrange/target | PoseInFrame | the target cut point, x axis along the branch (absent frames: no target) |
| /branchrange/timing | JSON {stage: ms} | per-stage timing, one series per stage in a Plot panel |
| /branchrange/result | JSON | the whole `branchrange/v1` result |
| /branchrange/tf | FrameTransforms | body_frd → camera (the mount); local_ned → body_frd once the pose is known |

3D entities are in the `camera` frame (rectified left camera, OpenCV axes, metres). The
transforms on /branchrange/tf place that frame on the vehicle and, once `set_vehicle_pose` gives
the vehicle's attitude and position, in the local NED frame: Foxglove's 3D panel with display
frame `local_ned` then shows the cut points where they are in the world. `deploy/foxglove_layout.json`
(written by `branchrange.onboard.foxglove_layout`) arranges these topics in one view.
"""

from __future__ import annotations

import json
import logging
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import cv2
import numpy as np

from branchrange.core.frame_result import SCHEMA_PATH, FrameResult
from branchrange.onboard.newest_slot import NewestSlot

log = logging.getLogger("branchrange.foxglove")

TOPICS = {
    "overlay": "/branchrange/overlay",
    "disparity": "/branchrange/disparity",
    "camera_info": "/branchrange/camera_info",
    "cut_points": "/branchrange/cut_points",
    "target": "/branchrange/target",
    "timing": "/branchrange/timing",
    "result": "/branchrange/result",
    "tf": "/branchrange/tf",
}
CAMERA_FRAME, BODY_FRAME, LOCAL_FRAME = "camera", "body_frd", "local_ned"
JPEG_QUALITY = 90
#: Length (m) of each drawn branch axis: from the base, past the cut point.
AXIS_LENGTH_M = 0.3
#: The smallest sphere drawn at a cut point, metres (a thin branch stays visible).
MIN_SPHERE_M = 0.03
TARGET_RGBA = (1.0, 0.1, 0.1, 1.0)
#: Branches: colour from low (orange) to high (green) confidence.
LOW_RGBA, HIGH_RGBA = (1.0, 0.6, 0.0, 0.9), (0.1, 0.9, 0.2, 0.9)
TIMING_SCHEMA = {
    "type": "object",
    "title": "branchrange timing (ms per stage)",
    "additionalProperties": {"type": "number"},
}


class FoxgloveTargetError(ValueError):
    """A `--foxglove` target that is neither an MCAP file nor a WebSocket address."""


@dataclass(frozen=True)
class FoxgloveTargets:
    """Where the sink sends: `mcap` (a new file; None: none) and/or a WebSocket server on `host`:`port`
    (`port` None: no server; 0: any free port)."""

    mcap: Path | None = None
    host: str = "127.0.0.1"
    port: int | None = None


def parse_targets(values: Sequence[str]) -> FoxgloveTargets:
    """Targets from `--foxglove` values: `FILE.mcap`, or `ws://HOST:PORT` (HOST default 127.0.0.1)."""
    mcap, host, port = None, "127.0.0.1", None
    for value in values:
        if value.startswith("ws://"):
            parts = urlsplit(value)
            try:
                parsed_port = parts.port
            except ValueError:
                parsed_port = None
            if parsed_port is None or parts.path not in ("", "/"):
                raise FoxgloveTargetError(
                    f"--foxglove {value!r}: expected ws://HOST:PORT (e.g. ws://127.0.0.1:8765; port 0 picks a free one)"
                )
            host, port = parts.hostname or host, parsed_port
        elif value.endswith(".mcap"):
            mcap = Path(value)
        else:
            raise FoxgloveTargetError(
                f"--foxglove {value!r}: expected an MCAP file (NAME.mcap) or a WebSocket address ws://HOST:PORT"
            )
    return FoxgloveTargets(mcap, host, port)


def _quaternion_x_to(direction: Sequence[float]) -> tuple[float, float, float, float]:
    """(x, y, z, w) of the shortest rotation taking the x axis onto `direction` (normalised here)."""
    d = np.asarray(direction, dtype=float)
    d = d / (np.linalg.norm(d) or 1.0)
    w = 1.0 + d[0]
    if w < 1e-9:  # opposite to x: half a turn about z
        return 0.0, 0.0, 1.0, 0.0
    q = np.array([0.0, -d[2], d[1], w])  # axis x × d, scalar 1 + x·d
    q /= np.linalg.norm(q)
    return float(q[0]), float(q[1]), float(q[2]), float(q[3])


def _jpeg(rgb: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError(f"OpenCV cannot encode a {rgb.shape} image as JPEG")
    return data.tobytes()


class FoxgloveSink:
    """Sends every frame's result (and images, when given) to Foxglove; see the module docstring.

    `targets`: an MCAP file and/or a WebSocket server. `mount` (a `branchrange.onboard.mavlink.CameraMount`)
    places the camera on the vehicle; without it the tree stops at `camera`. `newest_only=True` (the
    daemon) hands each frame to a thread of its own and returns at once, so encoding the images never
    delays the next result; a frame arriving while that thread is busy replaces the waiting one
    (`dropped` counts them). Otherwise (the replay) every frame is logged before the call returns.
    Use as a context manager or call `close()`: it logs the waiting frame, finishes the MCAP file and
    stops the server.
    """

    def __init__(
        self,
        targets: FoxgloveTargets,
        *,
        mount: Any = None,
        newest_only: bool = False,
        server_name: str = "branchrange",
    ) -> None:
        import foxglove
        from foxglove import channels

        if targets.mcap is None and targets.port is None:
            raise FoxgloveTargetError("no Foxglove target: give an MCAP file and/or a WebSocket port")
        self.targets, self.mount = targets, mount
        self._fg = foxglove
        self._context = foxglove.Context()  # this sink's own channels and sinks, apart from any other sink
        ctx = self._context
        self._overlay = channels.CompressedImageChannel(TOPICS["overlay"], context=ctx)
        self._disparity = channels.CompressedImageChannel(TOPICS["disparity"], context=ctx)
        self._camera_info = channels.CameraCalibrationChannel(TOPICS["camera_info"], context=ctx)
        self._cut_points = channels.SceneUpdateChannel(TOPICS["cut_points"], context=ctx)
        self._target = channels.PoseInFrameChannel(TOPICS["target"], context=ctx)
        self._tf = channels.FrameTransformsChannel(TOPICS["tf"], context=ctx)
        self._timing = foxglove.Channel(TOPICS["timing"], schema=TIMING_SCHEMA, context=ctx)
        result_schema = json.loads(SCHEMA_PATH.read_text(encoding="utf-8"))
        self._result = foxglove.Channel(TOPICS["result"], schema=result_schema, context=ctx)
        self._writer = self._server = None
        self._vehicle: tuple[np.ndarray, np.ndarray] | None = None
        self._pose_now: Callable[[], tuple[Sequence[float], Sequence[float]] | None] | None = None
        self.frames = 0
        self._slot = NewestSlot() if newest_only else None
        self._worker: threading.Thread | None = None
        try:
            if targets.mcap is not None:
                targets.mcap.parent.mkdir(parents=True, exist_ok=True)
                self._writer = foxglove.open_mcap(targets.mcap, allow_overwrite=True, context=ctx)
        except Exception as error:  # OSError, or the SDK's own error
            self.close()
            raise FoxgloveTargetError(
                f"--foxglove {targets.mcap}: cannot write the MCAP file ({error}); expected "
                "a .mcap path in a writable folder"
            ) from error
        try:
            if targets.port is not None:
                self._server = foxglove.start_server(
                    name=server_name, host=targets.host, port=targets.port, context=ctx
                )
        except Exception as error:  # the SDK's own error (address in use, unknown host)
            self.close()
            raise FoxgloveTargetError(
                f"--foxglove ws://{targets.host}:{targets.port}: cannot serve ({error}); "
                "expected a free port on an address of this machine (0 picks a free port)"
            ) from error
        if self._slot is not None:
            self._worker = threading.Thread(target=self._drain, name="foxglove", daemon=True)
            self._worker.start()

    @property
    def port(self) -> int | None:
        """The WebSocket server's port (the one picked when asked for port 0); None without a server."""
        return None if self._server is None else int(self._server.port)

    def describe(self) -> str:
        """Where the frames go, for logs: the MCAP file and/or the WebSocket address."""
        parts = [] if self.targets.mcap is None else [f"MCAP {self.targets.mcap}"]
        if self.port is not None:
            parts.append(f"live ws://{self.targets.host}:{self.port}")
        return ", ".join(parts)

    def set_vehicle_pose(self, position_ned_m: Sequence[float], attitude_wxyz: Sequence[float]) -> None:
        """The vehicle's position (local NED, metres) and attitude (unit quaternion w, x, y, z, body FRD → NED)
        for the next frames' local_ned → body_frd transform."""
        self._vehicle = (np.asarray(position_ned_m, dtype=float), np.asarray(attitude_wxyz, dtype=float))

    @property
    def dropped(self) -> int:
        """Frames replaced before the sink's thread got to them (`newest_only`; 0 otherwise)."""
        return 0 if self._slot is None else self._slot.replaced

    def follow_vehicle(self, pose_now: Callable[[], tuple[Sequence[float], Sequence[float]] | None]) -> None:
        """Ask `pose_now()` — (position local NED m, attitude w, x, y, z) or None, e.g. the MAVLink relay's
        `vehicle_pose` — before each frame, so the scene carries local_ned → body_frd while the vehicle's
        state is known (the daemon does this)."""
        self._pose_now = pose_now

    def __call__(self, result: FrameResult, artifacts: Any = None) -> None:
        """One frame: its result and, with `artifacts` (branchrange.core.pipeline.FrameArtifacts), its images."""
        if self._pose_now is not None and (pose := self._pose_now()) is not None:
            self.set_vehicle_pose(*pose)
        if self._slot is not None:
            self._slot.put((result, artifacts))
        else:
            self._log_frame(result, artifacts)

    def _drain(self) -> None:
        """The `newest_only` thread: log the newest frame handed over, until closed."""
        assert self._slot is not None
        while (item := self._slot.take()) is not None:
            try:
                self._log_frame(*item)
            except Exception:  # a frame the sink cannot show must not end the thread
                log.exception("frame %s not sent to Foxglove", item[0].frame.index)
            finally:
                self._slot.task_done()

    def _log_frame(self, result: FrameResult, artifacts: Any) -> None:
        """Log the frame's messages at its capture time (see the module docstring)."""
        fg = self._fg.messages
        stamp_ns = result.frame.timestamp_ns
        stamp = fg.Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
        if artifacts is not None:
            self._log_images(result, artifacts, stamp, stamp_ns)
        camera, frame = result.camera, result.frame
        f = camera.focal_px
        cx = (frame.width - 1) / 2 if camera.cx is None else camera.cx
        cy = (frame.height - 1) / 2 if camera.cy is None else camera.cy
        self._camera_info.log(
            fg.CameraCalibration(
                timestamp=stamp,
                frame_id=CAMERA_FRAME,
                width=frame.width,
                height=frame.height,
                distortion_model="plumb_bob",
                D=[0.0] * 5,
                K=[f, 0, cx, 0, f, cy, 0, 0, 1],
                R=[1, 0, 0, 0, 1, 0, 0, 0, 1],
                P=[f, 0, cx, 0, 0, f, cy, 0, 0, 0, 1, 0],
            ),
            log_time=stamp_ns,
        )
        self._cut_points.log(self._scene(result, stamp), log_time=stamp_ns)
        target = result.target
        if target is not None:
            x, y, z, w = _quaternion_x_to(target.axis)
            self._target.log(
                fg.PoseInFrame(
                    timestamp=stamp,
                    frame_id=CAMERA_FRAME,
                    pose=fg.Pose(
                        position=fg.Vector3(x=target.cut_point_m[0], y=target.cut_point_m[1], z=target.cut_point_m[2]),
                        orientation=fg.Quaternion(x=x, y=y, z=z, w=w),
                    ),
                ),
                log_time=stamp_ns,
            )
        transforms = self._transforms(stamp)
        if transforms:
            self._tf.log(fg.FrameTransforms(transforms=transforms), log_time=stamp_ns)
        self._timing.log({k: float(v) for k, v in result.timing_ms.items()}, log_time=stamp_ns)
        self._result.log(result.to_json_dict(), log_time=stamp_ns)
        self.frames += 1

    def _log_images(self, result: FrameResult, artifacts: Any, stamp: Any, stamp_ns: int) -> None:
        from branchrange.core.overlay import draw_overlay
        from stereo.io import colorize_disparity

        fg = self._fg.messages
        overlay = draw_overlay(artifacts.left, result, artifacts.masks)
        disparity = colorize_disparity(artifacts.disparity, max_disp=result.stereo.max_disparity)
        for channel, image in ((self._overlay, overlay), (self._disparity, disparity)):
            channel.log(
                fg.CompressedImage(timestamp=stamp, frame_id=CAMERA_FRAME, data=_jpeg(image), format="jpeg"),
                log_time=stamp_ns,
            )

    def _scene(self, result: FrameResult, stamp: Any) -> Any:
        """All branches of the frame as scene entities, after deleting the previous frame's."""
        fg = self._fg.messages
        entities = []
        for branch in result.branches:
            is_target = result.is_target(branch)
            c = branch.confidence
            rgba = TARGET_RGBA if is_target else tuple(lo + (hi - lo) * c for lo, hi in zip(LOW_RGBA, HIGH_RGBA))
            colour = fg.Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])
            cut, base, axis = (np.asarray(v, dtype=float) for v in (branch.cut_point_m, branch.base_m, branch.axis))
            size = max(branch.diameter_m * 1.5, MIN_SPHERE_M)
            label = (
                f"{'TARGET ' if is_target else ''}#{branch.id}  {branch.distance_m:.2f} m  "
                f"conf {c:.2f}  Ø {branch.diameter_m * 100:.1f} cm"
            )
            tip = base + axis * max(AXIS_LENGTH_M, float(np.linalg.norm(cut - base)) * 2)

            def point(p: np.ndarray) -> Any:
                return fg.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))

            def at(p: np.ndarray) -> Any:
                return fg.Pose(
                    position=fg.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])), orientation=fg.Quaternion(w=1.0)
                )

            entities.append(
                fg.SceneEntity(
                    timestamp=stamp,
                    frame_id=CAMERA_FRAME,
                    id=f"branch-{branch.id}",
                    metadata=[
                        fg.KeyValuePair(key="distance_m", value=f"{branch.distance_m:.4f}"),
                        fg.KeyValuePair(key="confidence", value=f"{c:.3f}"),
                        fg.KeyValuePair(key="target", value=str(is_target).lower()),
                    ],
                    spheres=[fg.SpherePrimitive(pose=at(cut), size=fg.Vector3(x=size, y=size, z=size), color=colour)],
                    lines=[
                        fg.LinePrimitive(
                            type=fg.LinePrimitiveLineType.LineStrip,
                            thickness=3.0,
                            scale_invariant=True,
                            points=[point(base), point(tip)],
                            color=colour,
                        )
                    ],
                    texts=[
                        fg.TextPrimitive(
                            pose=at(cut + np.array([0.0, -size, 0.0])),
                            billboard=True,
                            font_size=14.0,
                            scale_invariant=True,
                            color=colour,
                            text=label,
                        )
                    ],
                )
            )
        return fg.SceneUpdate(
            deletions=[fg.SceneEntityDeletion(timestamp=stamp, type=fg.SceneEntityDeletionType.All)], entities=entities
        )

    def _transforms(self, stamp: Any) -> list[Any]:
        """body_frd → camera (the mount) and local_ned → body_frd (the vehicle pose), those that are known."""
        from branchrange.onboard.mavlink.frames import quaternion_wxyz

        fg = self._fg.messages
        transforms = []
        if self.mount is not None:
            w, x, y, z = quaternion_wxyz(self.mount.camera_to_body)
            t = self.mount.translation_m
            transforms.append(
                fg.FrameTransform(
                    timestamp=stamp,
                    parent_frame_id=BODY_FRAME,
                    child_frame_id=CAMERA_FRAME,
                    translation=fg.Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                    rotation=fg.Quaternion(x=x, y=y, z=z, w=w),
                )
            )
        if self._vehicle is not None:
            position, (w, x, y, z) = self._vehicle
            norm = math.sqrt(w * w + x * x + y * y + z * z) or 1.0
            transforms.append(
                fg.FrameTransform(
                    timestamp=stamp,
                    parent_frame_id=LOCAL_FRAME,
                    child_frame_id=BODY_FRAME,
                    translation=fg.Vector3(x=float(position[0]), y=float(position[1]), z=float(position[2])),
                    rotation=fg.Quaternion(x=x / norm, y=y / norm, z=z / norm, w=w / norm),
                )
            )
        return transforms

    def close(self) -> None:
        """Log the waiting frame, finish the MCAP file and stop the server; idempotent."""
        if self._slot is not None and self._worker is not None:
            self._slot.close()
            self._worker.join(timeout=10)
            self._worker = None
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self._server is not None:
            self._server.stop()
            self._server = None

    def __enter__(self) -> FoxgloveSink:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
