"""Stereo frames → a ROS 2 bag (rosbag2, MCAP or SQLite) laid out as the ZED ROS 2 wrapper records it.

Used by `branchrange bag-from-recording` (our recordings to bags) and by the tests that need bags:
rectified left/right images on two topics with the same header stamp per pair, and each pair's
`sensor_msgs/CameraInfo` on two more (rectified: D zero, R identity, P with the right camera's
`Tx = -fx·B`), as ROS drivers publish them. A raw calibration is applied first (images rectified
with camera.Rectifier), so the bag always holds what the wrapper's rectified colour topics hold. Topic
names default to those of the wrapper since 5.1 (camera.sources.rosbag.BagTopics).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from camera.calibration import StereoCalibration
from camera.rectify import Rectifier
from camera.sources.frame import SourceConfigError, StereoFrame
from camera.sources.rosbag import CAMERA_INFO_TYPE, COMPRESSED_TYPE, IMAGE_TYPE, BagTopics

#: How images are stored: raw `sensor_msgs/Image` encodings, or `CompressedImage` formats.
RAW_ENCODINGS = {"bgra8": cv2.COLOR_RGB2BGRA, "bgr8": cv2.COLOR_RGB2BGR, "rgb8": None, "mono8": cv2.COLOR_RGB2GRAY}
COMPRESSED_FORMATS = {"jpeg": ".jpg", "png": ".png"}
STORAGES = ("mcap", "sqlite3")
#: The ZED wrapper publishes its colour images as bgra8.
DEFAULT_ENCODING = "bgra8"
FRAME_IDS = {"left": "zed_left_camera_optical_frame", "right": "zed_right_camera_optical_frame"}


class BagWriteError(ValueError):
    """The bag cannot be written as asked (existing path, unknown storage or encoding)."""


def _header(types: Any, stamp_ns: int, frame_id: str) -> Any:
    time = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
    return types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)


def image_message(types: Any, rgb: np.ndarray, stamp_ns: int, frame_id: str, encoding: str) -> Any:
    """A `sensor_msgs/Image` (raw encodings) or `CompressedImage` (jpeg, png) holding the RGB `uint8 H×W×3` image."""
    header = _header(types, stamp_ns, frame_id)
    if encoding in COMPRESSED_FORMATS:
        ok, data = cv2.imencode(COMPRESSED_FORMATS[encoding], cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        if not ok:
            raise BagWriteError(f"OpenCV cannot encode a {rgb.shape} image as {encoding}")
        return types[COMPRESSED_TYPE](header=header, format=encoding, data=data.ravel())
    conversion = RAW_ENCODINGS[encoding]
    pixels = rgb if conversion is None else cv2.cvtColor(rgb, conversion)
    height, width = pixels.shape[:2]
    step = pixels.strides[0]
    return types[IMAGE_TYPE](
        header=header,
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=step,
        data=np.ascontiguousarray(pixels).ravel(),
    )


def camera_info_message(types: Any, projection: np.ndarray, size: tuple[int, int], stamp_ns: int, frame_id: str) -> Any:
    """A rectified `sensor_msgs/CameraInfo`: K from P's first three columns, no distortion, R identity."""
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return types[CAMERA_INFO_TYPE](
        header=_header(types, stamp_ns, frame_id),
        height=size[1],
        width=size[0],
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=projection[:, :3].astype(np.float64).ravel(),
        r=np.eye(3).ravel(),
        p=projection.astype(np.float64).ravel(),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def write_bag(
    frames: Iterable[StereoFrame],
    calibration: StereoCalibration,
    out: str | Path,
    *,
    storage: str = "mcap",
    encoding: str = DEFAULT_ENCODING,
    topics: BagTopics = BagTopics(),
) -> int:
    """Write `frames` (RGB pairs at the calibration's size; stamps = the frames' timestamps, ns) to a new bag
    directory `out`; returns the number of pairs written. `storage`: "mcap" or "sqlite3"; `encoding`: one of
    RAW_ENCODINGS or COMPRESSED_FORMATS. Raises BagWriteError for bad options or an existing `out`, and the
    calibration's FrameSizeError for a frame of another size."""
    from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
    from rosbags.typesys import Stores, get_typestore

    if storage not in STORAGES:
        raise BagWriteError(f"storage is {storage!r}; expected one of {', '.join(STORAGES)}")
    if encoding not in RAW_ENCODINGS and encoding not in COMPRESSED_FORMATS:
        accepted = ", ".join([*RAW_ENCODINGS, *COMPRESSED_FORMATS])
        raise BagWriteError(f"encoding is {encoding!r}; expected one of {accepted}")
    store = get_typestore(Stores.ROS2_HUMBLE)
    types = store.types
    rectifier = Rectifier(calibration)
    image_type = COMPRESSED_TYPE if encoding in COMPRESSED_FORMATS else IMAGE_TYPE
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    try:
        writer = Writer(Path(out), version=Writer.VERSION_LATEST, storage_plugin=plugin)
    except WriterError as error:
        raise BagWriteError(f"{out}: {error}") from error
    written = 0
    with writer:
        connections = {
            topic: writer.add_connection(topic, msgtype, typestore=store)
            for topic, msgtype in (
                (topics.left, image_type),
                (topics.right, image_type),
                (topics.left_info, CAMERA_INFO_TYPE),
                (topics.right_info, CAMERA_INFO_TYPE),
            )
        }
        for frame in frames:
            left, right = rectifier.rectify(frame.left, frame.right)
            stamp = int(frame.timestamp_ns)
            messages = (
                (topics.left, image_message(types, left, stamp, FRAME_IDS["left"], encoding), image_type),
                (topics.right, image_message(types, right, stamp, FRAME_IDS["right"], encoding), image_type),
                (
                    topics.left_info,
                    camera_info_message(types, rectifier.P1, rectifier.size, stamp, FRAME_IDS["left"]),
                    CAMERA_INFO_TYPE,
                ),
                (
                    topics.right_info,
                    camera_info_message(types, rectifier.P2, rectifier.size, stamp, FRAME_IDS["right"]),
                    CAMERA_INFO_TYPE,
                ),
            )
            for topic, message, msgtype in messages:
                writer.write(connections[topic], stamp, store.serialize_cdr(message, msgtype))
            written += 1
    if written == 0:
        raise SourceConfigError(f"{out}: no frames to write")
    return written
