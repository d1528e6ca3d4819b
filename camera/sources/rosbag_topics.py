"""Where a ROS 2 bag keeps the calibration of an image topic: the `camera_info` topic next to it.

ROS drivers publish a camera's `sensor_msgs/CameraInfo` as `camera_info` in the namespace of its image, or
of a namespace above it when one camera publishes several images (raw, rectified, compressed). The ZED
wrapper since 5.1 publishes `/zed/zed_node/left/color/rect/image` beside `…/left/color/rect/camera_info`;
before 5.1 `/zed/zed_node/left/image_rect_color` beside `/zed/zed_node/left/camera_info`; image_transport
adds `/compressed` below either image. Walking up the image topic's namespace finds the info topic of
every one of them, without a table of driver names.

The walk stops below the namespace the left and right image topics share (`/zed/zed_node` for the ZED):
a `camera_info` there belongs to neither camera alone, and taking it for both would give a stereo pair
with one camera's projection twice.
"""

from __future__ import annotations

from collections.abc import Collection

#: The last name of a camera's CameraInfo topic (ROS image_transport and camera_info_manager convention).
CAMERA_INFO_NAME = "camera_info"


def namespaces(topic: str) -> list[str]:
    """The namespaces that hold `topic`, innermost first, ending with the root "/":
    `/zed/zed_node/left/image_rect_color` → `/zed/zed_node/left`, `/zed/zed_node`, `/zed`, `/`."""
    parts = [p for p in topic.split("/") if p]
    return ["/" + "/".join(parts[:depth]) for depth in range(len(parts) - 1, -1, -1)]


def camera_info_candidates(image_topic: str, other_image_topic: str) -> list[str]:
    """The `camera_info` topics that may hold `image_topic`'s calibration, nearest first: one per namespace of
    the image topic, up to (not including) the namespace it shares with the stereo partner `other_image_topic`."""
    shared = set(namespaces(other_image_topic))
    candidates = []
    for namespace in namespaces(image_topic):
        if namespace in shared:
            break
        candidates.append(f"{namespace.rstrip('/')}/{CAMERA_INFO_NAME}")
    return candidates


def find_camera_info(image_topic: str, other_image_topic: str, info_topics: Collection[str]) -> str | None:
    """The nearest of `camera_info_candidates` that is one of `info_topics` (the bag's CameraInfo topics);
    None when the bag has none of them."""
    return next((t for t in camera_info_candidates(image_topic, other_image_topic) if t in info_topics), None)
