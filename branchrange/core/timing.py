"""Stage timing shared by the per-frame stages: one dict of milliseconds per frame."""

from __future__ import annotations

import time


def lap_ms(timing: dict[str, float], stage: str, start: float) -> float:
    """Record the milliseconds since `start` (a `time.perf_counter()` value) under `stage`; returns now."""
    now = time.perf_counter()
    timing[stage] = round((now - start) * 1000.0, 3)
    return now
