"""Replay of ROS 2 bags (rosbag2, MCAP or SQLite) without a ROS installation, through the `rosbags` package.

A stereo camera under ROS 2 publishes its left and right images on two topics (`sensor_msgs/Image`
or `sensor_msgs/CompressedImage`) and their calibration on two `sensor_msgs/CameraInfo` topics.
`RosbagSource` pairs the two image streams by header stamp (within a tolerance: the ZED wrapper
stamps both views of a grab alike, other drivers nearly so), counts the images that found no
partner, and takes the calibration from the rectified projection matrices P of the two
CameraInfo messages (focal length and principal point from the left P, the baseline from the
right P's `Tx = -fx·B`) unless a calibration file is given. Image topics default to the ZED
ROS 2 wrapper's rectified colour topics: those of wrapper 5.1 and later
(`/zed/zed_node/left/color/rect/image`, …), or, in a bag that has only them, those of the wrappers
before 5.1 (`/zed/zed_node/left/image_rect_color`, …; logged). Each CameraInfo topic not named is the
`camera_info` topic next to its image topic, found by walking up the image topic's namespace
(camera.sources.rosbag_topics: either wrapper generation, raw or compressed, and other drivers' layouts).
Topics named in the spec are used as given. A bag cut short (a recording killed before rosbag2 finished it,
a copy interrupted) is reported as "truncated or unfinished", with what to do.

Spec (camera.sources.open_source): `rosbag:PATH[?left=TOPIC&right=TOPIC&left_info=TOPIC&right_info=TOPIC
&tolerance_ms=MS]`, PATH a bag directory (metadata.yaml), a `.mcap` or a `.db3` file; also the replay
options `start_at`, `start_signal`, `max_late_ms` (camera.sources.spec_options).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from camera.calibration import CalibrationError, StereoCalibration, from_rectified
from camera.sources.clock_sync import ClockSync
from camera.sources.frame import CorruptFrameError, SourceConfigError, SourceUnavailable, StereoFrame
from camera.sources.replay import DEFAULT_PERIOD_NS, FrameStamp, ReplaySource
from camera.sources.rosbag_topics import camera_info_candidates, find_camera_info
from camera.sources.spec_options import REPLAY_KEYS, split_spec

log = logging.getLogger("camera.sources.rosbag")

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
#: Raw image encodings read, and how each becomes RGB (None: already RGB).
ENCODINGS: dict[str, int | None] = {
    "rgb8": None,
    "bgr8": cv2.COLOR_BGR2RGB,
    "bgra8": cv2.COLOR_BGRA2RGB,
    "rgba8": cv2.COLOR_RGBA2RGB,
    "mono8": cv2.COLOR_GRAY2RGB,
}
#: Channels per pixel of each encoding.
CHANNELS = {"rgb8": 3, "bgr8": 3, "bgra8": 4, "rgba8": 4, "mono8": 1}
DEFAULT_TOLERANCE_MS = 5.0
#: A stereo baseline outside this range (metres) means a CameraInfo whose Tx is not -fx·B in metres.
BASELINE_RANGE_M = (0.005, 5.0)


@dataclass(frozen=True)
class BagTopics:
    """The four topics of a stereo camera in a bag; the defaults are the ZED ROS 2 wrapper's since its
    version 5.1 (namespace `/zed`, node `zed_node`), rectified colour images. A source that reads no
    CameraInfo (a calibration file given) holds "" for an info topic it neither was given nor found."""

    left: str = "/zed/zed_node/left/color/rect/image"
    right: str = "/zed/zed_node/right/color/rect/image"
    left_info: str = "/zed/zed_node/left/color/rect/camera_info"
    right_info: str = "/zed/zed_node/right/color/rect/camera_info"


#: The same topics as the ZED ROS 2 wrapper published them up to version 5.0.
ZED_TOPICS_BEFORE_5_1 = BagTopics(
    "/zed/zed_node/left/image_rect_color",
    "/zed/zed_node/right/image_rect_color",
    "/zed/zed_node/left/camera_info",
    "/zed/zed_node/right/camera_info",
)
#: How an MCAP file and an SQLite database (rosbag2's .db3) begin.
MCAP_MAGIC, SQLITE_MAGIC = b"\x89MCAP0\r\n", b"SQLite format 3\x00"


TOPIC_KEYS = ("left", "right", "left_info", "right_info")
SPEC_KEYS = (*TOPIC_KEYS, "tolerance_ms")


def parse_rosbag_spec(rest: str) -> tuple[Path, dict[str, str], float, list[tuple[str, str]]]:
    """(bag path, the topics the spec names by role (TOPIC_KEYS), pairing tolerance in ms, the replay options)
    from what follows `rosbag:` (see the module docstring and camera.sources.spec_options)."""
    path_text, options = split_spec(f"rosbag:{rest}", rest, (*SPEC_KEYS, *REPLAY_KEYS))
    if not path_text:
        raise SourceConfigError(
            f"source spec 'rosbag:{rest}': expected rosbag:PATH[?left=TOPIC&right=TOPIC&"
            "left_info=TOPIC&right_info=TOPIC&tolerance_ms=MS]"
        )
    topics: dict[str, str] = {}
    tolerance_ms = DEFAULT_TOLERANCE_MS
    for key, value in options:
        if key in REPLAY_KEYS:
            continue
        if key == "tolerance_ms":
            try:
                tolerance_ms = float(value)
            except ValueError:
                tolerance_ms = -1.0
            if not 0 <= tolerance_ms < 1000:
                raise SourceConfigError(
                    f"source spec 'rosbag:{rest}': tolerance_ms is {value!r}; expected a "
                    "number of milliseconds in [0, 1000)"
                )
        elif not value.startswith("/"):
            raise SourceConfigError(
                f"source spec 'rosbag:{rest}': {key} is {value!r}; expected a topic name starting with /"
            )
        else:
            topics[key] = value
    return Path(path_text), topics, tolerance_ms, [(k, v) for k, v in options if k in REPLAY_KEYS]


def stamp_ns(message: Any) -> int:
    """The message's header stamp in nanoseconds."""
    return int(message.header.stamp.sec) * 1_000_000_000 + int(message.header.stamp.nanosec)


def image_from_message(message: Any, msgtype: str, topic: str) -> np.ndarray:
    """The RGB `uint8 H×W×3` image of a `sensor_msgs/Image` (rgb8, bgr8, bgra8, rgba8, mono8) or a
    `sensor_msgs/CompressedImage` (JPEG/PNG). An unsupported encoding raises SourceConfigError (every
    message of the topic would fail); bytes that do not decode raise CorruptFrameError (this one only)."""
    data = np.asarray(message.data, dtype=np.uint8)
    if msgtype == COMPRESSED_TYPE:
        bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
        if bgr is None:
            raise CorruptFrameError(
                f"{topic}: a CompressedImage ({message.format!r}, {data.size} bytes) at "
                f"stamp {stamp_ns(message)} ns does not decode as JPEG or PNG"
            )
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    encoding = str(message.encoding).lower()
    if encoding not in ENCODINGS:
        raise SourceConfigError(
            f"{topic}: image encoding {message.encoding!r} is not supported; expected one of {', '.join(ENCODINGS)}"
        )
    height, width, step, channels = int(message.height), int(message.width), int(message.step), CHANNELS[encoding]
    if step < width * channels or data.size < step * height:
        raise CorruptFrameError(
            f"{topic}: a {width}×{height} {encoding} image at stamp {stamp_ns(message)} ns has "
            f"step {step} and {data.size} bytes; expected step ≥ {width * channels} and "
            f"{step * height} bytes"
        )
    pixels = data[: step * height].reshape(height, step)[:, : width * channels].reshape(height, width, channels)
    conversion = ENCODINGS[encoding]
    return np.ascontiguousarray(pixels) if conversion is None else cv2.cvtColor(pixels, conversion)


def calibration_from_camera_info(left: Any, right: Any, source: str) -> StereoCalibration:
    """The rectified calibration two CameraInfo messages describe, from their projection matrices P
    (3×4 row-major): f, cx, cy of the left P, cx of the right P, baseline B = -Tx/fx with Tx = P_right[0, 3].

    Raises CalibrationError naming the value when the pair is not a rectified pair with a
    plausible baseline (P all zeros, different focal lengths or rows, Tx of the wrong sign or unit).
    """
    p_left = np.asarray(left.p, dtype=float).reshape(3, 4)
    p_right = np.asarray(right.p, dtype=float).reshape(3, 4)
    fx, cx, cy = p_left[0, 0], p_left[0, 2], p_left[1, 2]
    if fx <= 0 or p_right[0, 0] <= 0:
        raise CalibrationError(
            source,
            "P",
            f"has fx = {fx} (left) and {p_right[0, 0]} (right)",
            "the rectified projection matrices of both cameras (fx > 0)",
        )
    if abs(p_right[0, 0] - fx) > 1e-3 * fx or abs(p_right[1, 2] - cy) > 0.5:
        raise CalibrationError(
            source,
            "P",
            f"left fx {fx:.3f}, cy {cy:.3f} and right fx {p_right[0, 0]:.3f}, cy {p_right[1, 2]:.3f} differ",
            "a rectified pair (same focal length and rows); or pass a calibration file",
        )
    baseline_m = -p_right[0, 3] / p_right[0, 0]
    low, high = BASELINE_RANGE_M
    if not low <= baseline_m <= high:
        raise CalibrationError(
            source,
            "P[0,3]",
            f"of the right camera is {p_right[0, 3]}, a baseline of {baseline_m} m",
            f"Tx = -fx·B with B in metres in [{low}, {high}]; or pass a calibration file",
        )
    return from_rectified(
        fx, cx, cy, baseline_m, (int(left.width), int(left.height)), cx_right=float(p_right[0, 2]), source=source
    )


class _BagFrames:
    """Stereo pairs of a bag in stamp order, for ReplaySource's pacing and looping (same reader protocol as
    its recording-directory and video readers)."""

    def __init__(self, path: Path, named: Mapping[str, str], tolerance_ns: int, use_camera_info: bool) -> None:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore

        self.path, self.tolerance_ns = path, tolerance_ns
        if not path.exists():
            raise SourceUnavailable(f"{path}: no such bag (expected a rosbag2 directory, a .mcap or a .db3 file)")
        try:
            self._reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            self._reader.open()
        except (AnyReaderError, OSError, ValueError, KeyError) as error:
            raise _unreadable(path, error) from error
        self._by_topic = {c.topic: c for c in self._reader.connections}
        left, right = self._image_topics(named)
        self._check_topic("left", left, (IMAGE_TYPE, COMPRESSED_TYPE))
        self._check_topic("right", right, (IMAGE_TYPE, COMPRESSED_TYPE))
        infos = {
            role: named.get(role) or self._camera_info_next_to(role, image, other, use_camera_info)
            for role, image, other in (("left_info", left, right), ("right_info", right, left))
        }
        if use_camera_info:
            for role, topic in infos.items():
                self._check_topic(role, topic, (CAMERA_INFO_TYPE,))
        self.topics = BagTopics(left, right, infos["left_info"], infos["right_info"])
        self.count: int | None = None  # pairs are known only once read
        self.unpaired = {"left": 0, "right": 0}
        self.use_camera_info = use_camera_info
        self._stamps: list[int] = []
        self._pairs: Iterator[tuple[Any, Any, int]] = iter(())
        self._pending: tuple[Any, Any, int] | None = None  # the pair `peek` read ahead
        self.seek(0)

    def _image_topics(self, named: Mapping[str, str]) -> tuple[str, str]:
        """(left, right) image topics: as named; one not named is the current ZED wrapper's; with neither named,
        the ZED wrapper's in this bag: those since 5.1, or those before when only they are there."""
        current, older = BagTopics(), ZED_TOPICS_BEFORE_5_1
        if "left" in named or "right" in named:
            return named.get("left", current.left), named.get("right", current.right)
        topics = self._by_topic.keys()
        if {current.left, current.right} <= topics or not {older.left, older.right} <= topics:
            return current.left, current.right
        log.info(
            "%s: reading the ZED wrapper's topics of before version 5.1 (%s, %s)", self.path, older.left, older.right
        )
        return older.left, older.right

    def _camera_info_next_to(self, role: str, image: str, other_image: str, needed: bool) -> str:
        """The bag's CameraInfo topic next to `image` (camera.sources.rosbag_topics); "" when there is none and
        it is not `needed`, else SourceConfigError naming the topics looked for and those the bag has."""
        infos = [t for t, c in self._by_topic.items() if c.msgtype == CAMERA_INFO_TYPE]
        found = find_camera_info(image, other_image, infos)
        if found is not None or not needed:
            return found or ""
        looked_for = ", ".join(camera_info_candidates(image, other_image)) or "none: both images share a namespace"
        self.close()
        raise SourceConfigError(
            f"{self.path}: no {CAMERA_INFO_TYPE} topic next to the image topic {image} (looked for {looked_for}); "
            f"its topics are: {self._listing()}. Name it in the spec (rosbag:PATH?{role}=TOPIC) "
            "or pass a calibration file"
        )

    def _listing(self) -> str:
        """The bag's topics with their types and message counts, for error messages."""
        connections = sorted(self._by_topic.values(), key=lambda c: c.topic)
        return "; ".join(f"{c.topic} ({c.msgtype}, {c.msgcount} messages)" for c in connections) or "none"

    def _check_topic(self, role: str, topic: str, types: tuple[str, ...]) -> None:
        connection = self._by_topic.get(topic)
        if connection is None:
            self.close()
            raise SourceConfigError(
                f"{self.path}: the {role} topic {topic} is not in the bag; its topics are: "
                f"{self._listing()}. Name the topics in the spec: rosbag:PATH?{role}=TOPIC"
            )
        if connection.msgtype not in types:
            self.close()
            raise SourceConfigError(
                f"{self.path}: the {role} topic {topic} carries {connection.msgtype}; expected {' or '.join(types)}"
            )

    @property
    def period_ns(self) -> int:
        """Median stamp step of the pairs read so far (the gap a loop leaves after the last frame)."""
        deltas = sorted(b - a for a, b in zip(self._stamps, self._stamps[1:]))
        return deltas[len(deltas) // 2] if deltas else DEFAULT_PERIOD_NS

    def _messages(self, *topics: str) -> Iterator[tuple[str, Any]]:
        """(topic, deserialised message) of `topics`, in bag order."""
        connections = [self._by_topic[t] for t in topics]
        for connection, _, raw in self._reader.messages(connections=connections):
            yield connection.topic, self._reader.deserialize(raw, connection.msgtype)

    def _paired(self) -> Iterator[tuple[Any, Any, int]]:
        """(left, right, pair index) messages matched by stamp (decoded by `read`, so a corrupt image does not end
        this generator): the older head of a queue whose partner cannot come any more
        (the other stream is already past it by more than the tolerance) is dropped and counted."""
        queues: dict[str, deque[Any]] = {"left": deque(), "right": deque()}
        roles = {self.topics.left: "left", self.topics.right: "right"}
        index = 0
        for topic, message in self._messages(self.topics.left, self.topics.right):
            queues[roles[topic]].append(message)
            while queues["left"] and queues["right"]:
                left, right = queues["left"][0], queues["right"][0]
                gap = stamp_ns(left) - stamp_ns(right)
                if abs(gap) <= self.tolerance_ns:
                    queues["left"].popleft(), queues["right"].popleft()
                    if index == len(self._stamps):
                        self._stamps.append(stamp_ns(left))
                    yield left, right, index
                    index += 1
                else:
                    older = "left" if gap < 0 else "right"
                    queues[older].popleft()
                    self.unpaired[older] += 1
        for role, queue in queues.items():
            self.unpaired[role] += len(queue)
        if any(self.unpaired.values()):
            log.warning(
                "%s: %d left and %d right images had no partner within %.1f ms and were skipped",
                self.path,
                self.unpaired["left"],
                self.unpaired["right"],
                self.tolerance_ns / 1e6,
            )

    def _frame(self, left: Any, right: Any, index: int) -> StereoFrame:
        left_type, right_type = self._by_topic[self.topics.left].msgtype, self._by_topic[self.topics.right].msgtype
        return StereoFrame(
            image_from_message(left, left_type, self.topics.left),
            image_from_message(right, right_type, self.topics.right),
            stamp_ns(left),
            index,
        )

    def seek(self, position: int) -> None:
        """Read from the bag's start again and skip `position` pairs (a bag has no pair index)."""
        self.unpaired = {"left": 0, "right": 0}
        self._pairs, self._pending = self._paired(), None
        for _ in range(position):
            if next(self._pairs, None) is None:
                break

    def peek(self) -> FrameStamp | None:
        """The next pair's stamp and index (its messages deserialised, its images not decoded); None at the end."""
        if self._pending is None:
            self._pending = next(self._pairs, None)
        return None if self._pending is None else (stamp_ns(self._pending[0]), self._pending[2])

    def _take(self) -> tuple[Any, Any, int] | None:
        pair = self._pending if self._pending is not None else next(self._pairs, None)
        self._pending = None
        return pair

    def skip(self) -> bool:
        """Pass over the next pair without decoding its images; False at the end of the bag."""
        return self._take() is not None

    def read(self) -> StereoFrame | None:
        """The next pair, None at the end of the bag; CorruptFrameError for a pair that does not decode."""
        pair = self._take()
        return None if pair is None else self._frame(*pair)

    def frame_size(self) -> tuple[int, int]:
        """(width, height) of the left images: of the first left message."""
        topic = self.topics.left
        for _, message in self._messages(topic):
            image = image_from_message(message, self._by_topic[topic].msgtype, topic)
            return int(image.shape[1]), int(image.shape[0])
        raise SourceUnavailable(f"{self.path}: the left topic {topic} has no messages")

    def recorded_fps(self) -> float:
        """(left messages − 1) / the bag's duration, seconds; 1e9 / DEFAULT_PERIOD_NS for a single message."""
        count, duration_ns = self._by_topic[self.topics.left].msgcount, self._reader.duration
        return (count - 1) * 1e9 / duration_ns if count > 1 and duration_ns > 0 else 1e9 / DEFAULT_PERIOD_NS

    def calibration(self) -> StereoCalibration | None:
        """The calibration of the first left and right CameraInfo messages (None when not asked to read them)."""
        if not self.use_camera_info:
            return None
        first: dict[str, Any] = {}
        for topic, message in self._messages(self.topics.left_info, self.topics.right_info):
            first.setdefault(topic, message)
            if len(first) == 2:
                return calibration_from_camera_info(
                    first[self.topics.left_info],
                    first[self.topics.right_info],
                    f"{self.path} {self.topics.left_info}, {self.topics.right_info}",
                )
        missing = [t for t in (self.topics.left_info, self.topics.right_info) if t not in first]
        raise SourceConfigError(f"{self.path}: no CameraInfo message on {', '.join(missing)}; pass a calibration file")

    def close(self) -> None:
        """Close the bag's files."""
        self._pairs, self._pending = iter(()), None
        self._reader.close()


def _unreadable(path: Path, error: Exception) -> SourceUnavailable:
    """The error for a bag rosbags cannot open: "truncated or unfinished" when it was cut short (see
    `_cut_short`), with what to do; else not a bag, with rosbags' reason."""
    reason = _cut_short(path)
    if reason is None:
        return SourceUnavailable(f"{path}: not a readable ROS 2 bag ({error})")
    folder = path if path.is_dir() else path.parent
    return SourceUnavailable(
        f"{path} is truncated or unfinished ({reason}): record it again or run `ros2 bag reindex {folder}`"
    )


def _cut_short(path: Path) -> str | None:
    """Why a bag that does not open looks cut short, None when it does not: a bag directory without the
    metadata.yaml rosbag2 writes when a recording ends, or a storage file that begins as MCAP or SQLite
    (so it was one) and yet does not open."""
    files = sorted(p for p in path.iterdir() if p.suffix in (".mcap", ".db3")) if path.is_dir() else [path]
    if path.is_dir() and files and not (path / "metadata.yaml").is_file():
        return "no metadata.yaml, which rosbag2 writes when a recording ends"
    for file in files:
        with file.open("rb") as stream:
            head = stream.read(len(SQLITE_MAGIC))
        if head.startswith(MCAP_MAGIC) or head.startswith(SQLITE_MAGIC):
            return f"{file.name} begins as a bag file but ends early or is damaged"
    return None


class RosbagSource(ReplaySource):
    """Replays the stereo pairs of a ROS 2 bag (see the module docstring), with ReplaySource's options:
    `pace` "recorded" (at the stamps' rate) or "fast", `loop`, `start` (pairs skipped). `calibration`
    overrides the CameraInfo topics; with `use_camera_info=False` they are neither needed nor read (the
    caller sets `calibration` after reading a file at `frame_size`). `topics` names topics by role
    (TOPIC_KEYS); those not named are found in the bag: the ZED wrapper's images in either naming, the
    CameraInfo next to each image topic (`topics` then holds the BagTopics read). `clock_sync`,
    `max_late_ms` as ReplaySource.
    Frame timestamps are the left images' header stamps, indices the pairs' positions in the bag.
    `unpaired` counts the images without a partner within `tolerance_ms` ({"left": n, "right": n},
    complete at the end of the bag).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        topics: Mapping[str, str] | None = None,
        tolerance_ms: float = DEFAULT_TOLERANCE_MS,
        use_camera_info: bool = True,
        pace: str = "recorded",
        loop: bool = False,
        start: int = 0,
        calibration: StereoCalibration | None = None,
        clock_sync: ClockSync | None = None,
        max_late_ms: float | None = None,
        clock: Callable[[], int] | None = None,
    ) -> None:
        self._named_topics = dict(topics or {})
        self.tolerance_ms, self.use_camera_info = tolerance_ms, use_camera_info
        options: dict[str, Any] = {} if clock is None else {"clock": clock}
        super().__init__(
            path,
            pace=pace,
            loop=loop,
            start=start,
            calibration=calibration,
            clock_sync=clock_sync,
            max_late_ms=max_late_ms,
            **options,
        )

    def _open_frames(self, fps: float | None) -> _BagFrames:
        # Kept under its own type too: the bag reader has more to say than a FrameReader.
        self._bag = _BagFrames(self.path, self._named_topics, int(round(self.tolerance_ms * 1e6)), self.use_camera_info)
        self.topics = self._bag.topics
        return self._bag

    @property
    def recorded_fps(self) -> float:
        """Left images per second over the bag's span (for an overlay video's rate; 30 when the bag says nothing)."""
        return self._bag.recorded_fps()

    @property
    def unpaired(self) -> dict[str, int]:
        """Images skipped for want of a partner so far, per side."""
        return dict(self._bag.unpaired)
