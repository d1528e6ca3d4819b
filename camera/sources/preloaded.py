"""A replay whose frames are decoded into memory before the first is released: a camera delivers raw frames,
so a benchmark that measures the loop (not the replay's PNG decoding) replays this way.

`PreloadedReplay` is a `ReplaySource` (same pacing: each frame released at its recorded timestamp, one that
cannot be on time dropped) over `DecodedFrames`, which reads every frame of another `FrameReader` up front.
Memory: an HD720 frame with its mask is 7.4 MB (0.8 GB for 110 frames, 1.1 GB for 150).
"""

from __future__ import annotations

from camera.calibration import StereoCalibration
from camera.sources.frame import StereoFrame
from camera.sources.replay import FrameReader, FrameStamp, ReplaySource


class DecodedFrames:
    """A `FrameReader` over another one's frames, all decoded into memory up front."""

    def __init__(self, reader: FrameReader) -> None:
        self.frames: list[StereoFrame] = []
        while (frame := reader.read()) is not None:
            self.frames.append(frame)
        self._period_ns, self._size, self._calibration = reader.period_ns, reader.frame_size(), reader.calibration()
        reader.close()
        self._position = 0

    @property
    def count(self) -> int:
        """Frames held."""
        return len(self.frames)

    @property
    def period_ns(self) -> int:
        """The recording's frame period, ns."""
        return self._period_ns

    def peek(self) -> FrameStamp | None:
        """(timestamp ns, index) of the next frame; None at the end."""
        if self._position >= len(self.frames):
            return None
        frame = self.frames[self._position]
        return frame.timestamp_ns, frame.index

    def read(self) -> StereoFrame | None:
        """The next frame, None at the end."""
        if self._position >= len(self.frames):
            return None
        self._position += 1
        return self.frames[self._position - 1]

    def skip(self) -> bool:
        """Pass over the next frame; False at the end."""
        return self.read() is not None

    def seek(self, position: int) -> None:
        """Make frame `position` (0-based) the next one read."""
        self._position = position

    def frame_size(self) -> tuple[int, int]:
        """(width, height) of each view, px."""
        return self._size

    def calibration(self) -> StereoCalibration | None:
        """The recording's calibration."""
        return self._calibration

    def close(self) -> None:
        """Nothing to release: the frames are in memory."""


class PreloadedReplay(ReplaySource):
    """A `ReplaySource` whose frames are decoded into memory before the first is released, then released at
    their recorded times: a camera delivers raw frames on time, while decoding three HD720 PNGs a frame on a
    busy 2-core computer falls behind, and a frame arriving late shows a pose older than the one the
    simulator flies at its arrival (7.4 MB an HD720 frame with its mask: 0.8 GB for 110 frames)."""

    def _open_frames(self, fps: float | None) -> FrameReader:
        return DecodedFrames(super()._open_frames(fps))
