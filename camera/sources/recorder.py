"""Recording stereo frames in the replay format (see camera.sources.recording_format)."""

from __future__ import annotations

import csv
from collections.abc import Callable, Iterable
from pathlib import Path

from camera.calibration import StereoCalibration
from camera.opencv_file import write_opencv_file
from camera.sources.frame import CorruptFrameError, StereoFrame
from camera.sources.image_files import write_mask, write_rgb
from camera.sources.recording_format import (
    CALIBRATION_NAME,
    MANIFEST_NAME,
    TIMESTAMP_COLUMNS,
    TIMESTAMPS_NAME,
    mask_name,
    write_manifest,
)

IMAGE_FORMATS = ("png", "jpg")


class Recorder:
    """Writes frames to a recording directory that `ReplaySource` replays.

    `calibration` is saved as calibration.yaml; `source_spec` is noted in the manifest;
    `image_format` is "png" (lossless, default) or "jpg". Frames with a `mask` have it saved as
    mask/NNNNNN.png; the first frame decides whether the recording carries masks, and every
    later frame must agree. The directory must be empty or new unless `overwrite` is set. Use
    as a context manager, or call `close()` to finish the manifest.

    A kill at any instant leaves a recording that replays up to its last complete frame: each
    image file appears atomically and a frame's timestamps.csv row is appended, flushed, only after
    all its files exist (camera.sources.recording_format).
    """

    def __init__(
        self,
        out_dir: str | Path,
        *,
        calibration: StereoCalibration | None = None,
        source_spec: str = "",
        image_format: str = "png",
        overwrite: bool = False,
    ) -> None:
        if image_format not in IMAGE_FORMATS:
            raise ValueError(f"image_format is {image_format!r}; expected one of {', '.join(IMAGE_FORMATS)}")
        self.directory = Path(out_dir)
        if self.directory.exists() and any(self.directory.iterdir()) and not overwrite:
            raise FileExistsError(f"{self.directory}: not empty; choose a new directory or allow overwriting")
        for sub in ("left", "right"):
            (self.directory / sub).mkdir(parents=True, exist_ok=True)
        self.image_format = image_format
        self.frames = 0
        self._size: tuple[int, int] | None = None
        self._first_ts: int | None = None
        self._last_ts: int | None = None
        self._manifest = {"source": source_spec, "image_format": image_format, "calibration": None, "masks": False}
        if calibration is not None:
            write_opencv_file(calibration, self.directory / CALIBRATION_NAME)
            self._manifest["calibration"] = CALIBRATION_NAME
        self._csv_file = (self.directory / TIMESTAMPS_NAME).open("w", newline="", encoding="utf-8")
        self._csv = csv.writer(self._csv_file)
        self._csv.writerow(TIMESTAMP_COLUMNS)
        self._csv_file.flush()
        self._write_manifest(complete=False)
        self._closed = False

    def write(self, frame: StereoFrame) -> None:
        """Append one pair; its views must keep the size of the first frame and its timestamp must increase."""
        if self._closed:
            raise ValueError(f"{self.directory}: recorder is closed")
        if self._size is None:
            self._size = frame.size
            self._manifest["masks"] = frame.mask is not None
            if frame.mask is not None:
                (self.directory / "mask").mkdir(exist_ok=True)
        elif frame.size != self._size:
            raise ValueError(
                f"frame {frame.index} is {frame.size[0]}×{frame.size[1]}; the recording is "
                f"{self._size[0]}×{self._size[1]}"
            )
        if self._last_ts is not None and frame.timestamp_ns <= self._last_ts:
            raise ValueError(
                f"frame {frame.index} timestamp {frame.timestamp_ns} ns does not follow "
                f"{self._last_ts} ns; expected increasing capture times"
            )
        if (frame.mask is not None) != self._manifest["masks"]:
            raise ValueError(
                f"frame {frame.index} {'has' if frame.mask is not None else 'lacks'} a mask; "
                f"the recording {'has' if self._manifest['masks'] else 'has no'} masks from its first frame"
            )
        if frame.mask is not None and frame.mask.shape != (self._size[1], self._size[0]):
            raise ValueError(
                f"frame {frame.index} mask has shape {frame.mask.shape}; expected "
                f"{self._size[1]}×{self._size[0]} like its images"
            )
        name = f"{self.frames:06d}.{self.image_format}"
        # The files first, each renamed into place whole; the row that makes the frame part of the recording last.
        write_rgb(self.directory / "left" / name, frame.left)
        write_rgb(self.directory / "right" / name, frame.right)
        if frame.mask is not None:
            write_mask(self.directory / mask_name(self.frames), frame.mask)
        self._csv.writerow([self.frames, frame.timestamp_ns, f"left/{name}", f"right/{name}"])
        self._csv_file.flush()
        if self._first_ts is None:
            self._first_ts = frame.timestamp_ns
        self._last_ts = frame.timestamp_ns
        self.frames += 1
        if self.frames == 1:  # size and masks are known now: an interrupted recording keeps them
            self._write_manifest(complete=False)

    def _write_manifest(self, complete: bool) -> None:
        width, height = self._size or (None, None)
        duration_s = ((self._last_ts or 0) - (self._first_ts or 0)) / 1e9
        fps = (self.frames - 1) / duration_s if self.frames > 1 and duration_s > 0 else None
        write_manifest(
            self.directory,
            {
                **self._manifest,
                "frames": self.frames,
                "width": width,
                "height": height,
                "first_timestamp_ns": self._first_ts,
                "last_timestamp_ns": self._last_ts,
                "fps": fps,
                "complete": complete,
            },
        )

    def close(self) -> Path:
        """Finish the recording (final manifest) and return the path of the manifest."""
        if not self._closed:
            self._closed = True
            self._csv_file.close()
            self._write_manifest(complete=True)
        return self.directory / MANIFEST_NAME

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def record(
    frames: Iterable[StereoFrame],
    recorder: Recorder,
    limit: int | None = None,
    on_frame: Callable[[StereoFrame], None] | None = None,
    on_corrupt: Callable[[CorruptFrameError], None] | None = None,
) -> int:
    """Write frames from `frames` (a source) into `recorder` until it ends or `limit` pairs are written.

    `on_frame` is called after each pair is written (a progress bar). A frame the source cannot
    decode is skipped and handed to `on_corrupt` when one is given (else the error propagates).
    Returns the number of pairs written.
    """
    written = 0
    iterator = iter(frames)
    while limit is None or written < limit:
        try:
            frame = next(iterator)
        except StopIteration:
            break
        except CorruptFrameError as error:
            if on_corrupt is None:
                raise
            on_corrupt(error)
            continue
        recorder.write(frame)
        written += 1
        if on_frame is not None:
            on_frame(frame)
    return written
