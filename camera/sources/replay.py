"""Replay of recorded stereo sequences: a recording directory, a plain folder of pairs, or a side-by-side video.

A folder of pairs is `DIR/left/*` and `DIR/right/*` image files (PNG, JPEG, BMP, TIFF) paired in
name order (digit runs compared as numbers, so `2.png` comes before `10.png`), with an optional
`DIR/mask/*` (one per pair, same order) and an optional `DIR/calibration.yaml`; it has no
timestamps, so frame i is stamped i / fps (default `PAIR_FOLDER_FPS`).

This is also the file-based camera the tests and the daemon's tests use in place of hardware.
"""

from __future__ import annotations

import logging
import re
import statistics
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import cv2

from camera.calibration import StereoCalibration
from camera.load import load_calibration
from camera.sources.frame import CorruptFrameError, SourceBase, SourceConfigError, SourceUnavailable, StereoFrame
from camera.sources.image_files import read_mask, read_rgb, split_side_by_side
from camera.sources.recording_format import (
    CALIBRATION_NAME,
    MANIFEST_NAME,
    TIMESTAMPS_NAME,
    RecordingFormatError,
    mask_name,
    read_manifest,
    read_timestamps,
)

#: Pacing modes: "recorded" waits so frames come at the recorded rate, "fast" returns them at once.
PACES = ("recorded", "fast")
DEFAULT_PERIOD_NS = 33_333_333
#: Frame rate given to a folder of pairs (which has no timestamps) unless `fps` says otherwise.
PAIR_FOLDER_FPS = 15.0
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")

log = logging.getLogger("camera.sources.replay")


class FrameReader(Protocol):
    """How `ReplaySource` reads one kind of container: frames in order, a position, and what it knows up front."""

    @property
    def count(self) -> int | None:
        """Frames in the container, None where it does not say before they are read."""

    @property
    def period_ns(self) -> int:
        """Nanoseconds between frames (recorded median or given rate)."""

    def read(self) -> StereoFrame | None:
        """The next frame, None at the end."""

    def seek(self, position: int) -> None:
        """Make frame `position` (0-based) the next one read."""

    def frame_size(self) -> tuple[int, int]:
        """(width, height) of each view in pixels."""

    def calibration(self) -> StereoCalibration | None:
        """The container's own calibration, None if it has none."""

    def close(self) -> None:
        """Release the files or handles."""


class _DirectoryFrames:
    """Frames of a recording directory, by position in timestamps.csv.

    Rows at the end whose files are missing or unreadable, and a last row cut off mid-write, are
    what a kill or a power cut while recording leaves (see camera.sources.recording_format): they
    are dropped and counted in `lost_at_end`, and replay ends at the last complete frame.
    """

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.manifest = read_manifest(directory)
        self.has_masks = bool(self.manifest.get("masks"))
        table = read_timestamps(directory)
        self.rows = table.rows
        self.lost_at_end = int(table.torn_last_row) + self._drop_unreadable_tail()
        if self.lost_at_end:
            log.warning(
                "%s: %d frame(s) lost at the end of the recording (power cut or kill while recording?)",
                directory,
                self.lost_at_end,
            )
        deltas = [b.timestamp_ns - a.timestamp_ns for a, b in zip(self.rows, self.rows[1:])]
        self.period_ns = int(statistics.median(deltas)) if deltas else DEFAULT_PERIOD_NS
        self.count = len(self.rows)
        self._position = 0

    def _drop_unreadable_tail(self) -> int:
        """Drop the rows at the end whose images (or mask) cannot be read; their number.

        Reads back from the last row to the first readable one (one frame decoded for a healthy
        recording). When no row at all is readable the recording was damaged, not interrupted: every
        row stays, and each frame raises CorruptFrameError when read.
        """
        readable = len(self.rows)
        while readable:
            try:
                self._load(readable - 1)
                break
            except CorruptFrameError:
                readable -= 1
        if not readable:
            return 0
        dropped = len(self.rows) - readable
        del self.rows[readable:]
        return dropped

    def _load(self, position: int) -> StereoFrame:
        """The frame of row `position` (recorded index, timestamp and mask); CorruptFrameError when unreadable."""
        row = self.rows[position]
        left = read_rgb(self.directory / row.left)
        right = read_rgb(self.directory / row.right)
        mask = read_mask(self.directory / mask_name(position)) if self.has_masks else None
        return StereoFrame(left, right, row.timestamp_ns, row.index, mask)

    def seek(self, position: int) -> None:
        """Make `position` (0-based row of timestamps.csv) the next frame read."""
        self._position = position

    def frame_size(self) -> tuple[int, int]:
        """(width, height) of one view: from the manifest, else (an interrupted recording) the first image."""
        width, height = self.manifest.get("width"), self.manifest.get("height")
        if isinstance(width, int) and isinstance(height, int):
            return width, height
        first = read_rgb(self.directory / self.rows[0].left)
        return int(first.shape[1]), int(first.shape[0])

    def read(self) -> StereoFrame | None:
        """The next frame (with the recorded index, timestamp and mask), None at the end of the recording."""
        if self._position >= self.count:
            return None
        position = self._position
        self._position += 1
        return self._load(position)

    def calibration(self) -> StereoCalibration | None:
        """The recording's calibration copy named in the manifest, None when it has none."""
        name = self.manifest.get("calibration")
        if not name:
            return None
        return load_calibration(self.directory / name, self.manifest.get("calibration_resolution"))

    def close(self) -> None:
        """Nothing stays open between reads."""


def _natural_key(name: str) -> list[int | str]:
    """Sort key comparing digit runs as numbers: frame_2 < frame_10."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def _images_in(folder: Path) -> list[Path]:
    return sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()),
        key=lambda p: _natural_key(p.name),
    )


class _PairFolderFrames:
    """Frames of a plain folder of pairs (`left/`, `right/`, optional `mask/`), stamped i / fps."""

    def __init__(self, directory: Path, fps: float | None) -> None:
        rate = PAIR_FOLDER_FPS if fps is None else fps
        if not rate > 0:
            raise SourceConfigError(f"fps is {fps}; expected a positive frame rate for a folder of pairs")
        self.directory = directory
        self.lefts, self.rights = _images_in(directory / "left"), _images_in(directory / "right")
        if not self.lefts or len(self.lefts) != len(self.rights):
            raise RecordingFormatError(
                f"{directory}: left/ holds {len(self.lefts)} images and right/ {len(self.rights)}; expected the same "
                f"number (at least one) of {'/'.join(IMAGE_SUFFIXES)} files, paired in name order"
            )
        self.masks = _images_in(directory / "mask") if (directory / "mask").is_dir() else []
        if self.masks and len(self.masks) != len(self.lefts):
            raise RecordingFormatError(
                f"{directory}: mask/ holds {len(self.masks)} images for {len(self.lefts)} pairs; "
                "expected one mask per pair (or no mask/ folder)"
            )
        self.period_ns = int(round(1e9 / rate))
        self.count = len(self.lefts)
        self._position = 0

    def seek(self, position: int) -> None:
        """Make `position` (0-based, in name order) the next pair read."""
        self._position = position

    def frame_size(self) -> tuple[int, int]:
        """(width, height) of one view, from the first left image."""
        first = read_rgb(self.lefts[0])
        return int(first.shape[1]), int(first.shape[0])

    def read(self) -> StereoFrame | None:
        """The next pair (index = position, timestamp = position / fps), None after the last."""
        if self._position >= self.count:
            return None
        position = self._position
        self._position += 1
        mask = read_mask(self.masks[position]) if self.masks else None
        return StereoFrame(
            read_rgb(self.lefts[position]), read_rgb(self.rights[position]), position * self.period_ns, position, mask
        )

    def calibration(self) -> StereoCalibration | None:
        """`DIR/calibration.yaml` when present, else None (pass one to ReplaySource or `--calibration`)."""
        path = self.directory / CALIBRATION_NAME
        return load_calibration(path) if path.is_file() else None

    def close(self) -> None:
        """Nothing stays open between reads."""


def _directory_frames(directory: Path, fps: float | None) -> _DirectoryFrames | _PairFolderFrames:
    """A recording (it has a manifest or timestamps) or else a folder of pairs (it has left/ and right/)."""
    if (directory / MANIFEST_NAME).is_file() or (directory / TIMESTAMPS_NAME).is_file():
        return _DirectoryFrames(directory)  # a damaged recording is reported as one, never read as plain pairs
    if (directory / "left").is_dir() and (directory / "right").is_dir():
        return _PairFolderFrames(directory, fps)
    raise RecordingFormatError(
        f"{directory}: neither a recording ({MANIFEST_NAME} missing) nor a folder of pairs "
        "(left/ and right/ image folders); expected one of the two"
    )


class _VideoFrames:
    """Frames of a side-by-side video file (left half | right half), timestamps from the frame rate."""

    def __init__(self, path: Path, fps: float | None) -> None:
        self.path = path
        self._capture: cv2.VideoCapture | None = None
        capture = self._open()
        reported = capture.get(cv2.CAP_PROP_FPS)
        rate = fps if fps is not None else reported
        if not rate or rate <= 0:
            raise SourceConfigError(f"{path}: the video reports no frame rate; pass fps= to replay it")
        self.period_ns: int = int(round(1e9 / rate))
        self.count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) or None

    def _open(self) -> cv2.VideoCapture:
        """The video (re)opened at its first frame; also kept as `self._capture`."""
        if self._capture is not None:
            self._capture.release()
        capture = self._capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            raise SourceUnavailable(
                f"{self.path}: OpenCV cannot open this video; expected a side-by-side "
                "stereo video (e.g. .avi/.mkv/.mp4) readable by OpenCV's FFmpeg backend"
            )
        self._position = 0
        return capture

    def frame_size(self) -> tuple[int, int]:
        """(width, height) of one view: half the video's width, its full height."""
        assert self._capture is not None
        return (
            int(self._capture.get(cv2.CAP_PROP_FRAME_WIDTH)) // 2,
            int(self._capture.get(cv2.CAP_PROP_FRAME_HEIGHT)),
        )

    def seek(self, position: int) -> None:
        """Reopen and read forward to `position` (exact, unlike codec-dependent seeking)."""
        self._open()
        while self._position < position and self._grab():
            pass

    def _grab(self) -> bool:
        assert self._capture is not None
        if not self._capture.grab():
            return False
        self._position += 1
        return True

    def read(self) -> StereoFrame | None:
        """The next frame, None at the end of the video."""
        assert self._capture is not None
        ok, bgr = self._capture.read()
        if not ok:
            return None
        index = self._position
        self._position += 1
        left, right = split_side_by_side(bgr)
        return StereoFrame(left, right, index * self.period_ns, index)

    def calibration(self) -> StereoCalibration | None:
        """None: a video carries no calibration (pass one to ReplaySource)."""
        return None

    def close(self) -> None:
        """Release the video file."""
        if self._capture is not None:
            self._capture.release()
            self._capture = None


class ReplaySource(SourceBase):
    """Replays a recording directory (`branchrange record` layout), a folder of pairs or a side-by-side video file.

    `pace="recorded"` waits so frames come at the recorded rate, `"fast"` as fast as they decode.
    `loop=True` starts again at `start` after the last frame; indices then keep growing (recorded
    index + pass × frame count) and timestamps keep increasing by the sequence's duration.
    `start` is the position (0-based) of the first frame replayed. `calibration` overrides the
    recording's own copy (a video has none: pass one, or leave it None). `fps` overrides a video's
    frame rate and sets a folder of pairs' (default 15). A frame whose image cannot be decoded
    raises CorruptFrameError; the next call goes on.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        pace: str = "recorded",
        loop: bool = False,
        start: int = 0,
        calibration: StereoCalibration | None = None,
        fps: float | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if pace not in PACES:
            raise SourceConfigError(f"pace is {pace!r}; expected one of {', '.join(PACES)}")
        if start < 0:
            raise SourceConfigError(f"start is {start}; expected a frame position ≥ 0")
        self.path = Path(path)
        self._frames: FrameReader = self._open_frames(fps)
        if self._frames.count is not None and start >= self._frames.count:
            raise SourceConfigError(f"start is {start}; {self.path} has {self._frames.count} frames")
        self.calibration = calibration if calibration is not None else self._frames.calibration()
        self.pace, self.loop, self.start = pace, loop, start
        self._clock = clock
        self._stop = threading.Event()
        self._frames.seek(start)
        self._pass = 0
        self._offset_ns = 0
        self._io_lock = threading.Lock()
        self._first_ts: int | None = None
        self._last_ts: int | None = None
        self._last_index = -1
        self._wall_start: int | None = None
        self._stream_start: int | None = None

    def _open_frames(self, fps: float | None) -> FrameReader:
        """The frame reader of `self.path`; a subclass replaying another container (camera.sources.rosbag)
        returns its own."""
        if self.path.is_dir():
            return _directory_frames(self.path, fps)
        if self.path.is_file():
            return _VideoFrames(self.path, fps)
        raise SourceUnavailable(f"{self.path}: no such recording directory or video file")

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) of each view in pixels, known before the first frame is read."""
        return self._frames.frame_size()

    @property
    def fps(self) -> float:
        """Frames per second: the recording's median rate, the video's, or the one given to a folder of pairs."""
        return 1e9 / self._frames.period_ns

    @property
    def frame_count(self) -> int | None:
        """Frames in the recording (None for a video whose container does not say)."""
        return self._frames.count

    @property
    def frames_lost_at_end(self) -> int:
        """Frames a recording directory lists at its end but cannot give (killed or powered off while
        recording; they are not replayed); 0 for every other container."""
        return self._frames.lost_at_end if isinstance(self._frames, _DirectoryFrames) else 0

    def __next__(self) -> StereoFrame:
        with self._io_lock:
            if self._stop.is_set():
                raise StopIteration
            frame = self._frames.read()
            if frame is None:
                frame = self._wrap()
        if self._pass == 0:
            if self._first_ts is None:
                self._first_ts = frame.timestamp_ns
            self._last_ts, self._last_index = frame.timestamp_ns, frame.index
        frame = StereoFrame(
            frame.left,
            frame.right,
            frame.timestamp_ns + self._offset_ns,
            frame.index + self._pass * (self._last_index + 1),
            frame.mask,
        )
        self._wait_for(frame.timestamp_ns)
        if self._stop.is_set():
            raise StopIteration
        return frame

    def _wrap(self) -> StereoFrame:
        """Go back to `start` when looping (StopIteration otherwise) and read the first frame again."""
        if not self.loop or self._first_ts is None or self._last_ts is None:
            raise StopIteration
        self._pass += 1
        self._offset_ns += self._last_ts - self._first_ts + self._frames.period_ns
        self._frames.seek(self.start)
        frame = self._frames.read()
        if frame is None:
            raise StopIteration
        return frame

    def _wait_for(self, timestamp_ns: int) -> None:
        if self.pace == "fast":
            return
        now = self._clock()
        if self._wall_start is None or self._stream_start is None:
            self._wall_start, self._stream_start = now, timestamp_ns
            return
        delay_ns = (timestamp_ns - self._stream_start) - (now - self._wall_start)
        if delay_ns > 0:
            self._stop.wait(delay_ns / 1e9)

    def close(self) -> None:
        """Stop replaying (a paced wait in another thread returns at once) and release the video."""
        self._stop.set()
        with self._io_lock:
            self._frames.close()
