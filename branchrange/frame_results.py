"""One source frame → its `branchrange/v1` result and JSONL line, shared by the daemon and the offline replay.

Both build their pipeline with `pipeline_for` and run every frame through `process_frame`, so
replaying a recording after a flight gives the results the daemon computed in the air (the
timing aside), and both write the same log lines.
"""
from __future__ import annotations

import json
from typing import Any

from branchrange.config import Config, pipeline_config
from camera.sources import SourceError, StereoFrame


def pipeline_for(cfg: Config, calibration: Any) -> Any:
    """The `Pipeline` that `[stereo]` and `[cutpoints]` describe, for a source's calibration, with
    its stereo backend already built: a missing checkpoint or a max_disp the backend cannot use
    fails here, at start-up, rather than as a rejected frame on every frame.

    Raises `SourceError` naming `camera.source` when the source brought no calibration, and the
    backend's `ValueError` (`BackendConfigError`, `CheckpointError`) when it cannot be built.
    """
    from branchrange.pipeline import Pipeline

    if calibration is None:
        raise SourceError(f"{cfg.camera.source}: no calibration; set camera.calibration")
    pipeline = Pipeline(pipeline_config(cfg), calibration=calibration)
    _ = pipeline.backend  # the property builds it
    return pipeline


def process_frame(pipeline: Any, frame: StereoFrame) -> dict[str, Any]:
    """The frame's result: its pair, its mask when the recording carries one, its index and capture time.

    Raises `ValueError` (the pipeline's input or geometry errors) when the pipeline rejects the frame.
    """
    return pipeline.process(frame.left, frame.right, mask=frame.mask, index=frame.index,
                            timestamp_ns=frame.timestamp_ns)


def result_line(result: dict[str, Any]) -> str:
    """The result as one compact JSON line, newline included: the results log format."""
    return json.dumps(result, separators=(",", ":")) + "\n"
