"""Overlay videos a person can watch: RGB frames into an MPEG-4 (mp4v) .mp4, or MJPG .avi when the
OpenCV build cannot write mp4v; and a check that the written file reads back frame for frame."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger("branchrange.overlay_video")


@dataclass(frozen=True)
class VideoCodec:
    """A codec to try: the FourCC written, the file suffix it goes in, and the FourCCs a reader may report."""

    fourcc: str
    suffix: str
    reads_back_as: tuple[str, ...]


#: Tried in order: MPEG-4 Part 2 plays almost everywhere; Motion-JPEG in AVI is in every OpenCV build.
#: FFmpeg reads mp4v back as 'FMP4' (its name for the same MPEG-4 Part 2 stream).
DEFAULT_CODECS = (VideoCodec("mp4v", ".mp4", ("mp4v", "FMP4")), VideoCodec("MJPG", ".avi", ("MJPG",)))


class VideoWriteError(OSError):
    """No codec could write the video, or the file does not read back as written; the message says which."""


def _fourcc_text(code: int) -> str:
    """The four characters of an integer FourCC (as `VideoCapture.get(CAP_PROP_FOURCC)` gives it)."""
    return "".join(chr((int(code) >> (8 * i)) & 0xFF) for i in range(4))


class OverlayVideoWriter:
    """Writes RGB `uint8 H×W×3` frames of one size at `fps` frames per second.

    The file opens on the first frame (its size fixes the video's). The first of `codecs` that
    OpenCV can open is used; when that is not the first, a warning names the codec and the new
    path (the suffix follows the codec: `out.mp4` becomes `out.avi`). `path` is where it went.
    """

    def __init__(self, path: str | Path, fps: float, codecs: tuple[VideoCodec, ...] = DEFAULT_CODECS) -> None:
        if not fps > 0:
            raise ValueError(f"video fps = {fps!r}: expected a positive frame rate")
        if not codecs:
            raise ValueError("no video codec to try")
        self.requested = Path(path)
        self.path = self.requested
        self.fps = float(fps)
        self.codecs = codecs
        self.codec: VideoCodec | None = None
        self.size: tuple[int, int] | None = None
        self.frames = 0
        self._writer: cv2.VideoWriter | None = None

    def _open(self, size: tuple[int, int]) -> None:
        self.requested.parent.mkdir(parents=True, exist_ok=True)
        for codec in self.codecs:
            path = self.requested.with_suffix(codec.suffix)
            writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec.fourcc), self.fps, size)
            if writer.isOpened():
                if codec is not self.codecs[0]:
                    log.warning(
                        "the %s codec is not available in this OpenCV build; writing %s video to %s instead",
                        self.codecs[0].fourcc,
                        codec.fourcc,
                        path,
                    )
                self._writer, self.codec, self.path, self.size = writer, codec, path, size
                return
            writer.release()
        tried = ", ".join(f"{c.fourcc} ({c.suffix})" for c in self.codecs)
        raise VideoWriteError(f"{self.requested}: OpenCV cannot write a video with any of {tried}")

    def write(self, frame_rgb: np.ndarray) -> None:
        """Append one RGB `uint8 H×W×3` frame; every frame must have the first one's size."""
        if frame_rgb.dtype != np.uint8 or frame_rgb.ndim != 3 or frame_rgb.shape[2] != 3:
            raise ValueError(f"video frame is {frame_rgb.dtype} of shape {frame_rgb.shape}; expected uint8 H×W×3 RGB")
        size = (int(frame_rgb.shape[1]), int(frame_rgb.shape[0]))
        if self._writer is None:
            self._open(size)
        elif size != self.size:
            raise ValueError(
                f"video frame {self.frames} is {size[0]}×{size[1]} px; the video is {self.size[0]}×{self.size[1]}"
            )
        assert self._writer is not None
        self._writer.write(cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2BGR))
        self.frames += 1

    def close(self) -> None:
        """Finish the file (idempotent)."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None

    def __enter__(self) -> OverlayVideoWriter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def check_video(path: str | Path, codec: VideoCodec, frames: int, size: tuple[int, int]) -> None:
    """Reopen a written video and decode it: it must report one of `codec`'s FourCCs, have `frames`
    frames (counted by decoding, not from the container) of `size` (width, height px).

    Raises `VideoWriteError` naming the file and what differs.
    """
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise VideoWriteError(f"{path}: OpenCV cannot reopen the video it wrote")
        reported = int(capture.get(cv2.CAP_PROP_FOURCC))
        if reported not in {cv2.VideoWriter_fourcc(*name) for name in codec.reads_back_as}:
            raise VideoWriteError(
                f"{path}: reads back as FourCC {_fourcc_text(reported)!r}; expected one of "
                f"{', '.join(codec.reads_back_as)}"
            )
        decoded = 0
        while True:
            ok, image = capture.read()
            if not ok:
                break
            if (image.shape[1], image.shape[0]) != tuple(size):
                raise VideoWriteError(
                    f"{path}: frame {decoded} is {image.shape[1]}×{image.shape[0]} px; expected {size[0]}×{size[1]}"
                )
            decoded += 1
    finally:
        capture.release()
    if decoded != frames:
        raise VideoWriteError(f"{path}: {decoded} frames decode; {frames} were written")
