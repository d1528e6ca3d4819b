"""Pipelines for the stereo worker processes' tests: built in the worker (picklable factories), slowed per frame."""

from __future__ import annotations

import time
from typing import Any

from branchrange.config.loader import Config, pipeline_for


def slowed_pipeline(cfg: Config, calibration: Any, delays_s: dict[int, float], default_s: float = 0.0) -> Any:
    """`pipeline_for(cfg, calibration)` whose stereo stage first sleeps `delays_s[frame index]` s (else
    `default_s`): frames finish in another order than they were captured, or after a chosen age."""
    pipeline = pipeline_for(cfg, calibration)
    stage = pipeline.stereo_stage

    def slowed(left, right, mask=None, index=0, timestamp_ns=0, shed_level=0):  # type: ignore[no-untyped-def]
        time.sleep(delays_s.get(index, default_s))
        return stage(left, right, mask, index, timestamp_ns, shed_level)

    pipeline.stereo_stage = slowed
    return pipeline
