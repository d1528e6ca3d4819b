"""Frame sources: live cameras (ZED over UVC, OAK over depthai), replay of recordings (`PreloadedReplay`: decoded
into memory first, for benchmarks of the loop alone), and wrappers.

Every source is an iterator of `StereoFrame` with `close()`, `calibration` and `is_lost` (see
camera.sources.frame). `OakSource`/`OakConfig` import depthai on first use only, `RosbagSource`/`BagTopics`
(ROS 2 bags) import rosbags on first use only.
"""

from __future__ import annotations

from typing import Any

from camera.sources.faults import FaultInjectingSource, FaultPlan
from camera.sources.frame import (
    Backoff,
    CorruptFrameError,
    SourceBase,
    SourceConfigError,
    SourceDisconnected,
    SourceError,
    SourceUnavailable,
    StereoFrame,
    StereoSource,
)
from camera.sources.latest import LatestFrameSource
from camera.sources.preloaded import PreloadedReplay
from camera.sources.recorder import Recorder, record
from camera.sources.recording_format import RecordingFormatError
from camera.sources.replay import ReplaySource
from camera.sources.spec import open_source
from camera.sources.zed_uvc import ZED_MODES, ZedUvcSource

__all__ = [
    "Backoff",
    "BagTopics",
    "CorruptFrameError",
    "FaultInjectingSource",
    "FaultPlan",
    "LatestFrameSource",
    "OakConfig",
    "OakSource",
    "PreloadedReplay",
    "Recorder",
    "RecordingFormatError",
    "ReplaySource",
    "RosbagSource",
    "SourceBase",
    "SourceConfigError",
    "SourceDisconnected",
    "SourceError",
    "SourceUnavailable",
    "StereoFrame",
    "StereoSource",
    "ZED_MODES",
    "ZedUvcSource",
    "open_source",
    "record",
]


def __getattr__(name: str) -> Any:
    if name in ("OakSource", "OakConfig"):
        from camera.sources import oak

        return getattr(oak, name)
    if name in ("RosbagSource", "BagTopics"):
        from camera.sources import rosbag

        return getattr(rosbag, name)
    raise AttributeError(f"module 'camera.sources' has no attribute {name!r}")
