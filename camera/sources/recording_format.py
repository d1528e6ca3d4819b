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
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

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
    path = directory / MANIFEST_NAME
    temporary = path.with_suffix(".json.tmp")
    temporary.write_text(
        json.dumps({"format": FORMAT_NAME, "version": FORMAT_VERSION, **manifest}, indent=2) + "\n", encoding="utf-8"
    )
    temporary.replace(path)


def read_timestamps(directory: Path) -> list[TimestampRow]:
    """The rows of timestamps.csv, checked for the header, integer fields and increasing timestamps."""
    path = directory / TIMESTAMPS_NAME
    try:
        handle = path.open(newline="", encoding="utf-8")
    except FileNotFoundError:
        raise RecordingFormatError(
            f"{path}: missing; expected a CSV with columns {','.join(TIMESTAMP_COLUMNS)}"
        ) from None
    rows: list[TimestampRow] = []
    with handle:
        reader = csv.reader(handle)
        header = next(reader, None)
        if header is None or tuple(h.strip() for h in header) != TIMESTAMP_COLUMNS:
            raise RecordingFormatError(f"{path}: header is {header}; expected {','.join(TIMESTAMP_COLUMNS)}")
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
        raise RecordingFormatError(f"{path}: has no frames; expected at least one row")
    return rows
