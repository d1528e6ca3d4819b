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
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import cv2

from camera.calibration import StereoCalibration
from camera.load import load_calibration
from camera.sources.clock_sync import ClockSync, StartInstant
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
#: Decode times (and wake-up delays) remembered to predict the next (a replay starts that much before the slot).
DECODE_HISTORY = 8
#: (recorded timestamp ns, recorded index) of a frame, known before its images are decoded.
FrameStamp = tuple[int, int]

log = logging.getLogger("camera.sources.replay")


class FrameReader(Protocol):
    """How `ReplaySource` reads one kind of container: frames in order, a position, and what it knows up front."""

    @property
    def count(self) -> int | None:
        """Frames in the container, None where it does not say before they are read."""

    @property
    def period_ns(self) -> int:
        """Nanoseconds between frames (recorded median or given rate)."""

    def peek(self) -> FrameStamp | None:
        """(recorded timestamp ns, index) of the next frame, found without decoding it; None at a known end."""

    def read(self) -> StereoFrame | None:
        """The next frame, decoded; None at the end."""

    def skip(self) -> bool:
        """Pass over the next frame without decoding its images; False at the end."""

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

    def __init__(self, directory: Path, with_masks: bool) -> None:
        self.directory = directory
        self.manifest = read_manifest(directory)
        self.has_masks = with_masks and bool(self.manifest.get("masks"))
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

    def peek(self) -> FrameStamp | None:
        """The next row's timestamp and index; None after the last row."""
        if self._position >= self.count:
            return None
        row = self.rows[self._position]
        return row.timestamp_ns, row.index

    def skip(self) -> bool:
        """Move past the next row; False after the last."""
        self._position += 1
        return self._position <= self.count

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

    def __init__(self, directory: Path, fps: float | None, with_masks: bool) -> None:
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
        self.masks = _images_in(directory / "mask") if with_masks and (directory / "mask").is_dir() else []
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

    def peek(self) -> FrameStamp | None:
        """The next pair's timestamp (position / fps) and index (position); None after the last."""
        return None if self._position >= self.count else (self._position * self.period_ns, self._position)

    def skip(self) -> bool:
        """Move past the next pair; False after the last."""
        self._position += 1
        return self._position <= self.count

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


def _directory_frames(directory: Path, fps: float | None, with_masks: bool) -> _DirectoryFrames | _PairFolderFrames:
    """A recording (it has a manifest or timestamps) or else a folder of pairs (it has left/ and right/);
    `with_masks=False` leaves their masks unread."""
    if (directory / MANIFEST_NAME).is_file() or (directory / TIMESTAMPS_NAME).is_file():
        return _DirectoryFrames(directory, with_masks)  # a damaged recording is reported as one, never as pairs
    if (directory / "left").is_dir() and (directory / "right").is_dir():
        return _PairFolderFrames(directory, fps, with_masks)
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

    def peek(self) -> FrameStamp | None:
        """The next frame's timestamp (position / fps) and index, never None: a video's frame count is only
        an estimate, so its end is found by `read` or `skip`."""
        return self._position * self.period_ns, self._position

    def skip(self) -> bool:
        """Grab the next frame without converting it (the codec still decodes it); False at the end."""
        return self._grab()

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

    `pace="recorded"` releases frames at the recorded rate, `"fast"` as fast as they decode.
    `loop=True` starts again at `start` after the last frame; indices then keep growing (recorded
    index + pass × frame count) and timestamps keep increasing by the sequence's duration.
    `start` is the position (0-based) of the first frame replayed. `calibration` overrides the
    recording's own copy (a video has none: pass one, or leave it None). `fps` overrides a video's
    frame rate and sets a folder of pairs' (default 15). `ignore_masks=True` leaves a recording's
    masks unread (frames come without, as from a live camera). `clock_sync` delays the first frame
    to a start time and announces its release (camera.sources.clock_sync). A frame whose image
    cannot be decoded raises CorruptFrameError; the next call goes on.

    Pacing keeps to a schedule, as a camera does: frame i is due at `start + (t_i − t_0)`, `start`
    being the release of the first frame. The replay waits for a frame's slot *before* decoding it,
    starting early by the longest of the last DECODE_HISTORY decode times plus the longest recent
    wake-up delay (how much later than asked a wait returned: a busy machine's scheduler), so that
    the frame is ready at its slot. A frame that would reach the consumer more than `late_limit_ns`
    after its slot is dropped, as a camera drops the frames nobody read in time: before decoding
    when the typical (median) decode time already makes it late, so no time goes to a frame that
    cannot be on time and the replay catches up; after decoding when that decode (or the wait for
    the slot) overran. The
    limit is half a frame period (later, the frame is nearer its successor's slot than its own),
    or `max_late_ms` (a simulator kept in step may want it tighter; the daemon takes a frame's
    release as its capture time, so a late release hides its lateness from the latency figures).
    Drops are counted in `dropped_late`; delivered frames keep their recorded timestamps and
    indices, so a consumer sees the gap.
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
        ignore_masks: bool = False,
        clock_sync: ClockSync | None = None,
        max_late_ms: float | None = None,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if pace not in PACES:
            raise SourceConfigError(f"pace is {pace!r}; expected one of {', '.join(PACES)}")
        if max_late_ms is not None and not max_late_ms > 0:
            raise SourceConfigError(f"max_late_ms is {max_late_ms}; expected milliseconds > 0 (None: half a period)")
        if start < 0:
            raise SourceConfigError(f"start is {start}; expected a frame position ≥ 0")
        self.path = Path(path)
        self.ignore_masks = ignore_masks
        self._frames: FrameReader = self._open_frames(fps)
        if self._frames.count is not None and start >= self._frames.count:
            raise SourceConfigError(f"start is {start}; {self.path} has {self._frames.count} frames")
        self.calibration = calibration if calibration is not None else self._frames.calibration()
        self.pace, self.loop, self.start, self.clock_sync = pace, loop, start, clock_sync
        self._clock = clock
        self._stop = threading.Event()
        self._frames.seek(start)
        self._pass = 0
        self._offset_ns = 0
        self._io_lock = threading.Lock()
        self._first_ts: int | None = None
        self._last_ts: int | None = None
        self._last_index = -1
        self._wrapped_without_frame = False
        self._start_clock_ns: int | None = None  # `clock` at the release of the first frame
        self._start_stamp_ns = 0  # that frame's (looped) timestamp
        self._max_late_ns = None if max_late_ms is None else round(max_late_ms * 1e6)
        self._decode_ns: deque[int] = deque(maxlen=DECODE_HISTORY)
        self._oversleep_ns: deque[int] = deque(maxlen=DECODE_HISTORY)
        self._dropped_late = 0

    def _open_frames(self, fps: float | None) -> FrameReader:
        """The frame reader of `self.path`; a subclass replaying another container (camera.sources.rosbag)
        returns its own."""
        if self.path.is_dir():
            return _directory_frames(self.path, fps, not self.ignore_masks)
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

    @property
    def dropped_late(self) -> int:
        """Frames dropped unseen because they could no longer be released on time (recorded pace)."""
        return self._dropped_late

    @property
    def late_limit_ns(self) -> int:
        """How late after its slot a frame may still be released: `max_late_ms`, else half a period."""
        return self._frames.period_ns // 2 if self._max_late_ns is None else self._max_late_ns

    def __next__(self) -> StereoFrame:
        with self._io_lock:
            while (frame := self._next_on_time()) is None:
                pass
            return frame

    def _next_on_time(self) -> StereoFrame | None:
        """The next frame, released at its slot; None when it was dropped late or the replay looped."""
        if self._stop.is_set():
            raise StopIteration
        stamp = self._frames.peek()
        if stamp is None:
            self._wrap()
            return None
        due = self._due(stamp[0] + self._offset_ns)
        if due is not None and self.pace == "recorded":
            typical = int(statistics.median(self._decode_ns)) if self._decode_ns else 0
            if self._clock() + typical > due + self.late_limit_ns:
                self._drop_unread(stamp)
                return None
            self._sleep_until(due - max(self._decode_ns, default=0) - max(self._oversleep_ns, default=0))
        frame = self._read(stamp)
        if frame is None:
            return None
        if due is None:
            self._begin(frame)
        elif self.pace == "recorded":
            self._sleep_until(due)
            if self._clock() > due + self.late_limit_ns:  # the decode overran, or the wait woke too late
                self._dropped_late += 1
                return None
        if self._stop.is_set():
            raise StopIteration
        return frame

    def _due(self, timestamp_ns: int) -> int | None:
        """The `clock()` ns at which the frame stamped `timestamp_ns` (this pass) is due; None before the start."""
        if self._start_clock_ns is None:
            return None
        return self._start_clock_ns + timestamp_ns - self._start_stamp_ns

    def _drop_unread(self, stamp: FrameStamp) -> None:
        """Pass over a frame too late to be worth decoding, and count it."""
        if not self._frames.skip():
            self._wrap()
            return
        self._note(stamp)
        self._dropped_late += 1

    def _read(self, stamp: FrameStamp) -> StereoFrame | None:
        """Decode the frame `stamp` announced, restamped for the current pass; None (after wrapping) at the end."""
        started = self._clock()
        try:
            frame = self._frames.read()
        except CorruptFrameError:
            self._note(stamp)  # it had its place in the sequence
            raise
        if frame is None:
            self._wrap()
            return None
        self._decode_ns.append(self._clock() - started)
        self._note(stamp)
        return StereoFrame(
            frame.left,
            frame.right,
            frame.timestamp_ns + self._offset_ns,
            frame.index + self._pass * (self._last_index + 1),
            frame.mask,
        )

    def _note(self, stamp: FrameStamp) -> None:
        """Remember the first pass's span (for the timestamps of the next passes)."""
        self._wrapped_without_frame = False
        if self._pass == 0:
            if self._first_ts is None:
                self._first_ts = stamp[0]
            self._last_ts, self._last_index = stamp

    def _begin(self, first: StereoFrame) -> None:
        """Start the schedule at the release of `first`: after the start time, announced (clock_sync)."""
        if self.clock_sync is not None:
            self.clock_sync.wait_for_start(self._stop)
            if self._stop.is_set():  # closed while waiting: it never started, so nothing is announced
                raise StopIteration
        self._start_clock_ns, wall_ns = self._clock(), time.time_ns()
        self._start_stamp_ns = first.timestamp_ns
        if self.clock_sync is not None:
            self.clock_sync.announce(
                StartInstant(str(self.path), wall_ns, self._start_clock_ns, first.timestamp_ns, first.index)
            )

    def _wrap(self) -> None:
        """Go back to `start` when looping; StopIteration otherwise, or when a pass gave no frame at all."""
        if not self.loop or self._first_ts is None or self._last_ts is None or self._wrapped_without_frame:
            raise StopIteration
        self._wrapped_without_frame = True
        self._pass += 1
        self._offset_ns += self._last_ts - self._first_ts + self._frames.period_ns
        self._frames.seek(self.start)

    def _sleep_until(self, deadline_ns: int) -> None:
        """Wait until `clock()` reaches `deadline_ns` (at once when close() is called); note how late it woke."""
        delay_ns = deadline_ns - self._clock()
        if delay_ns > 0:
            self._stop.wait(delay_ns / 1e9)
            self._oversleep_ns.append(max(0, self._clock() - deadline_ns))

    def close(self) -> None:
        """Stop replaying (a paced wait in another thread returns at once) and release the video."""
        self._stop.set()
        with self._io_lock:
            self._frames.close()
