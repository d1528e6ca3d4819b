"""The on-disk layout of a recorded sequence, shared by the recorder (writer) and the replay source (reader).

```
DIR/recording.json    manifest: {"format": "branchrange-recording", "version": 1, "frames": N,
                      "width": W, "height": H, "image_format": "png", "calibration": "calibration.yaml"
                      or null, "source": "zed:0", "complete": true, "first_timestamp_ns": …,
                      "last_timestamp_ns": …, "fps": …}
DIR/timestamps.csv    header "index,timestamp_ns,left,right", one row per pair, paths relative to DIR
DIR/left/000000.png   left views (RGB content, written through OpenCV as usual image files)
DIR/right/000000.png  right views
DIR/calibration.yaml  the calibration as an OpenCV FileStorage file (camera.opencv_file), if known
DIR/mask/000000.png   optional: the left view's branch mask (8/16-bit PNG, instance ids), present for
                      every frame when the manifest says "masks": true (synthetic or annotated data)
```
The manifest is written when recording starts (`complete: false`), again after the first frame
(size, masks) and on close, and timestamps.csv is appended frame by frame, so an interrupted
recording still replays, with its masks.

Surviving a kill or a power cut at any instant: every image appears atomically (written as a hidden
`.NAME.tmp`, then renamed, camera.sources.atomic_file) and a frame's row is appended to
timestamps.csv (and flushed) only once all its files exist. A kill therefore leaves at most a
stray temporary file and a last row cut off before its line end, which `read_timestamps` drops.
There is no fsync (it would cost more than a frame's budget on SD cards and eMMC): after a power
cut the kernel may not yet have written the last seconds, so rows at the end may name missing or
empty images; the replay source drops those trailing rows and counts them as frames lost at the
end. A damaged row anywhere else is a format error (a cut-off line) or a corrupt frame (an image).
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from camera.sources.atomic_file import replace_atomically
from camera.sources.frame import SourceUnavailable

FORMAT_NAME = "branchrange-recording"
FORMAT_VERSION = 1
MANIFEST_NAME = "recording.json"
TIMESTAMPS_NAME = "timestamps.csv"
TIMESTAMP_COLUMNS = ("index", "timestamp_ns", "left", "right")
CALIBRATION_NAME = "calibration.yaml"


def mask_name(position: int) -> str:
    """Path, relative to the recording directory, of the mask of the pair at `position` in timestamps.csv."""
    return f"mask/{position:06d}.png"


class RecordingFormatError(SourceUnavailable):
    """A recording directory is incomplete or malformed; the message names the file and what was expected."""


@dataclass(frozen=True)
class TimestampRow:
    """One line of timestamps.csv: the pair's index, capture time (ns) and image paths relative to the directory."""

    index: int
    timestamp_ns: int
    left: str
    right: str


def read_manifest(directory: Path) -> dict[str, Any]:
    """The manifest of a recording directory, checked for its format name and version."""
    path = directory / MANIFEST_NAME
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RecordingFormatError(
            f"{path}: missing; expected the manifest of a recording made by `branchrange record`"
        ) from None
    except json.JSONDecodeError as error:
        raise RecordingFormatError(f"{path}: not valid JSON ({error.msg} at line {error.lineno})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT_NAME:
        raise RecordingFormatError(
            f"{path}: format is {manifest.get('format') if isinstance(manifest, dict) else manifest!r}; "
            f"expected {FORMAT_NAME!r}"
        )
    if manifest.get("version") != FORMAT_VERSION:
        raise RecordingFormatError(f"{path}: version is {manifest.get('version')!r}; expected {FORMAT_VERSION}")
    return manifest


def write_manifest(directory: Path, manifest: dict[str, Any]) -> None:
    """Write the manifest atomically (a partial file never replaces a good one)."""
    text = json.dumps({"format": FORMAT_NAME, "version": FORMAT_VERSION, **manifest}, indent=2) + "\n"
    replace_atomically(directory / MANIFEST_NAME, text.encode("utf-8"))


@dataclass(frozen=True)
class TimestampTable:
    """timestamps.csv read: its complete rows, and whether a last row cut off mid-write was dropped."""

    rows: list[TimestampRow]
    torn_last_row: bool


def _split_torn_last_line(text: str) -> tuple[str, bool]:
    """`text` without a last line that lacks its line end (a write cut off by a kill), and whether there was one.

    The recorder ends every row with a line break in one flushed write, so only the very last line
    can be cut off; a line that ends but does not parse is damage, not an interrupted write.
    """
    if not text or text.endswith("\n"):
        return text, False
    cut = text.rfind("\n") + 1
    return text[:cut], True


def read_timestamps(directory: Path) -> TimestampTable:
    """The rows of timestamps.csv, checked for the header, integer fields and increasing timestamps.

    A last line cut off before its line end is dropped (`torn_last_row`); any other malformed line
    is a RecordingFormatError naming it.
    """
    path = directory / TIMESTAMPS_NAME
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise RecordingFormatError(
            f"{path}: missing; expected a CSV with columns {','.join(TIMESTAMP_COLUMNS)}"
        ) from None
    complete, torn = _split_torn_last_line(text)
    reader = csv.reader(io.StringIO(complete, newline=""))
    header = next(reader, None)
    if header is None or tuple(h.strip() for h in header) != TIMESTAMP_COLUMNS:
        raise RecordingFormatError(f"{path}: header is {header}; expected {','.join(TIMESTAMP_COLUMNS)}")
    rows: list[TimestampRow] = []
    for line_number, fields in enumerate(reader, start=2):
        if not fields:
            continue
        try:
            row = TimestampRow(int(fields[0]), int(fields[1]), fields[2], fields[3])
        except (ValueError, IndexError):
            raise RecordingFormatError(
                f"{path}: line {line_number} reads {fields}; expected "
                "integer index, integer timestamp_ns, left path, right path"
            ) from None
        if rows and row.timestamp_ns <= rows[-1].timestamp_ns:
            raise RecordingFormatError(
                f"{path}: line {line_number}: timestamp_ns {row.timestamp_ns} does not "
                f"increase (previous {rows[-1].timestamp_ns}); expected monotonic times"
            )
        rows.append(row)
    if not rows:
        cut_off = " (its only row was cut off mid-write)" if torn else ""
        raise RecordingFormatError(f"{path}: has no complete frames{cut_off}; expected at least one row")
    return TimestampTable(rows, torn)
