"""Stereo as it runs, for the randomized scenes: the SGBM disparity of the rendered pair, then dropout.

The network sees what the project's SGBM stage makes of the pair (holes, streaks, wrong matches on
thin branches), not the exact disparity. On top of that, disparity *dropout* blanks the whole frame
or some regions of it (0 = invalid, what the stereo stage reports where it has nothing), as when the
depth stream stalls, the sun blinds one camera or a lens is wet: the image alone must then still
carry the masks.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Dropout:
    """How disparity drops out: the whole frame with probability `frame_probability`, 1 to `max_regions`
    elliptic regions, each up to `max_region_fraction` of the image width across, with probability
    `region_probability`, else not at all."""

    frame_probability: float = 0.1
    region_probability: float = 0.3
    max_regions: int = 4
    max_region_fraction: float = 0.5


def sgbm_disparity(left: np.ndarray, right: np.ndarray, max_disp: int) -> np.ndarray:
    """The project's SGBM disparity (float32 `H×W` px, 0 where invalid) of a rectified uint8 RGB pair."""
    from stereo.backends import make_backend

    return make_backend("sgbm", max_disp=max_disp).compute(left, right).disparity.astype(np.float32)


def dropout_kind(rng: np.random.Generator, dropout: Dropout) -> str:
    """Whether a frame's disparity drops out: 'frame' (all of it), 'regions' or 'none', as `dropout` draws it."""
    draw = rng.random()
    if draw < dropout.frame_probability:
        return "frame"
    return "regions" if draw < dropout.frame_probability + dropout.region_probability else "none"


def dropped_out(disparity: np.ndarray, rng: np.random.Generator, kind: str, dropout: Dropout) -> np.ndarray:
    """`disparity` `H×W` with the whole frame (`kind` 'frame') or 1 to `dropout.max_regions` elliptic regions
    ('regions') set to 0 (invalid); as it was for 'none'."""
    out = disparity.copy()
    if kind == "frame":
        out[:] = 0.0
        return out
    if kind != "regions":
        return out
    height, width = out.shape
    holes = np.zeros((height, width), dtype=np.uint8)
    for _ in range(int(rng.integers(1, dropout.max_regions + 1))):
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        axes = tuple(int(max(2, width * dropout.max_region_fraction * rng.uniform(0.1, 0.5))) for _ in range(2))
        cv2.ellipse(holes, centre, axes, float(rng.uniform(0, 180)), 0.0, 360.0, 1, -1)
    out[holes > 0] = 0.0
    return out
