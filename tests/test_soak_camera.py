"""The soak's camera (`benchmarks/soak_daemon.SoakCamera`) keeps the faults it is told: an unplugged or stalled
camera delivers nothing, not even the frame it was reading when the fault began.

Why: the soak judges the daemon's "camera lost" against the faults it injected; a frame delivered from inside an
unplug (stamped 0.9 s into it on a starved CPU, seed 12) made the daemon truthfully say "camera back", and the
soak called that a status hiding the fault (`health_untrue`).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from soak_daemon import CameraFaults, SoakCamera  # noqa: E402

from camera.sources import StereoFrame  # noqa: E402


class _UnpluggedWhileReading:
    """A replay whose first read ends after the camera was unplugged (for `seconds`) meanwhile."""

    calibration = None

    def __init__(self, faults: CameraFaults, kind: str, seconds: float) -> None:
        self.faults, self.kind, self.seconds, self.reads = faults, kind, seconds, 0
        self.until = 0.0

    def __next__(self) -> StereoFrame:
        if self.reads == 0:
            self.until = time.monotonic() + self.seconds
            self.faults.apply({"fault": self.kind, "until": self.until})
        self.reads += 1
        image = np.zeros((4, 4), np.uint8)
        return StereoFrame(image, image, 0, self.reads - 1)

    def close(self) -> None:
        pass


def test_a_frame_read_while_the_camera_was_unplugged_or_stalled_is_not_delivered():
    for kind in ("disconnect", "stall"):
        faults = CameraFaults()
        inner = _UnpluggedWhileReading(faults, kind, 0.2)
        camera = SoakCamera(inner, faults)
        frame = next(camera)
        assert frame.index == 1, kind  # the frame read during the fault never arrived
        assert frame.timestamp_ns >= inner.until * 1e9, kind  # the next one was captured after it
        camera.close()
