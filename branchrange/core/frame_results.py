"""One source frame → its `branchrange/v1` result and JSONL line, shared by the daemon and the offline replay.

Both build their pipeline with `branchrange.config.loader.pipeline_for` and hand every frame to it through
`stereo_stage` (the daemon then runs `geometry_stage` on its own thread; the replay runs both in `process_frame`),
so replaying a recording after a flight gives the results the daemon computed in the air (the
timing aside), and both write the same log lines.

A results log starts each run with a header line (`run_header_line`): `{"schema":
"branchrange/run-header/v1", "version", "config_sha256", "started_utc", "source", "kind"}`, so
runs appended to one file stay apart. When the daemon's camera is reopened within a run, frame
indices and timestamps start again from the new source's; a marker line (`camera_reopened_line`:
`{"schema": "branchrange/camera-reopened/v1", "event": "camera_reopened", "reason", "reopens",
"reopened_utc", "first_index", "first_timestamp_ns"}`) comes just before the first result after it.
`read_runs` gives back a log's JSON records grouped by run; `read_results` its frame results as typed
`FrameResult`s (`FrameResult.from_json_dict`), headers and markers skipped.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from branchrange.core.frame_result import FrameResult
from camera.sources import StereoFrame


def stereo_stage(pipeline: Any, frame: StereoFrame, shed_level: int = 0) -> Any:
    """The stereo half of the frame (`Pipeline.stereo_stage`): its pair, its mask when the recording
    carries one, its index and capture time, at the daemon's work level `shed_level`
    (`branchrange.onboard.load_shedding`). The daemon's stereo thread calls it, then
    `pipeline.geometry_stage` on its geometry thread.

    Raises `ValueError` (the pipeline's input or geometry errors) when the pipeline rejects the frame.
    """
    return pipeline.stereo_stage(frame.left, frame.right, frame.mask, frame.index, frame.timestamp_ns, shed_level)


def process_frame(pipeline: Any, frame: StereoFrame) -> FrameResult:
    """The frame's result: both halves in a row, exactly as the daemon runs them on two threads.

    Raises `ValueError` (the pipeline's input or geometry errors) when the pipeline rejects the frame.
    """
    result: FrameResult = pipeline.geometry_stage(stereo_stage(pipeline, frame))
    return result


def json_line(record: dict[str, Any]) -> str:
    """A JSON object as one compact line, newline included: the results log format."""
    return json.dumps(record, separators=(",", ":")) + "\n"


def result_line(result: FrameResult) -> str:
    """A frame's result as one results-log line."""
    return json_line(result.to_json_dict())


RUN_HEADER_SCHEMA = "branchrange/run-header/v1"


def config_sha256(cfg: Any) -> str:
    """SHA-256 (hex) of the effective configuration, every key sorted: equal hashes, equal settings."""
    text = json.dumps(dataclasses.asdict(cfg), sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def utc_now() -> str:
    """The UTC time now as the logs write it: ISO 8601 to the millisecond, with a Z."""
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def run_header(kind: str, cfg: Any, source: str) -> dict[str, Any]:
    """The header of one run: what wrote it (`kind`, e.g. "replay" or "daemon"), the package
    version, the configuration's hash, the UTC start time (ISO 8601, ms) and the source spec."""
    from stereo.cli import package_version

    return {
        "schema": RUN_HEADER_SCHEMA,
        "version": package_version(),
        "config_sha256": config_sha256(cfg),
        "started_utc": utc_now(),
        "source": source,
        "kind": kind,
    }


def run_header_line(kind: str, cfg: Any, source: str) -> str:
    """`run_header(...)` as one JSON line, newline included: the first line a run writes to its log."""
    return json_line(run_header(kind, cfg, source))


def is_run_header(record: Any) -> bool:
    """Whether a parsed log line is a run header (not a frame result)."""
    return isinstance(record, dict) and record.get("schema") == RUN_HEADER_SCHEMA


CAMERA_REOPENED_SCHEMA = "branchrange/camera-reopened/v1"


def camera_reopened_line(reason: str, reopens: int, reopened_utc: str, first: FrameResult) -> str:
    """The marker line written before `first`, the first result after the camera was reopened: why
    (`reason`), the how-manyth reopening of the run (`reopens`), when (`reopened_utc`), and the frame
    index and timestamp (ns) the results go on from — the new source's, which may restart lower."""
    return json_line(
        {
            "schema": CAMERA_REOPENED_SCHEMA,
            "event": "camera_reopened",
            "reason": reason,
            "reopens": reopens,
            "reopened_utc": reopened_utc,
            "first_index": first.frame.index,
            "first_timestamp_ns": first.frame.timestamp_ns,
        }
    )


def is_camera_reopened(record: Any) -> bool:
    """Whether a parsed log line is a camera-reopened marker (not a frame result)."""
    return isinstance(record, dict) and record.get("schema") == CAMERA_REOPENED_SCHEMA


def read_runs(path: str | Path) -> list[tuple[dict[str, Any] | None, list[dict[str, Any]]]]:
    """The runs of a results log as JSON records: (header, frame results) each; results before any
    header (logs written before headers existed) come as a run whose header is None. Blank lines and
    camera-reopened markers are skipped."""
    runs: list[tuple[dict[str, Any] | None, list[dict[str, Any]]]] = []
    with open(path, encoding="utf-8") as stream:
        for record in (json.loads(line) for line in stream if line.strip()):
            if is_run_header(record):
                runs.append((record, []))
            elif not is_camera_reopened(record):
                if not runs:
                    runs.append((None, []))
                runs[-1][1].append(record)
    return runs


def read_results(path: str | Path) -> Iterator[FrameResult]:
    """Every frame result of a results log, in order, run headers skipped.

    Raises `ResultFormatError` (a ValueError) naming the key of a line that is not a `branchrange/v1` result.
    """
    for _, results in read_runs(path):
        yield from (FrameResult.from_json_dict(record) for record in results)
