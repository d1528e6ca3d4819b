"""Which frames of a recording are worth labelling: diverse ones the segmenters are unsure about, spaced in time.

Each candidate frame is described by cheap statistics (`FrameStats`): a colour histogram of its left
view, its mean valid disparity (how near the scene is), the mean confidence of its cut points, how
far the learned and the structure segmenters agree on its branch pixels, and how many of its branches
flicker against the frames scored before and after it (`with_flicker`). `select_frames` then picks
greedily (farthest-point sampling, weighted by uncertainty):

- uncertainty `u_i = ((1 − c_i) + (1 − a_i) + f_i) / 3`, `c_i` the mean cut-point confidence (0 without
  any cut point: nothing was found confidently), `a_i` the IoU of the two segmenters' branch pixels
  (1 when neither finds a branch) and `f_i` the flicker: `(lonely + missed) / (K_i + missed)`, of the
  frame's `K_i` cut points those with none within `FLICKER_GATE_M` in either neighbouring frame
  (appeared, then vanished), plus the neighbours' cut points found in both of them but not here (0
  when there is nothing to count, and in the first and last frame);
- distance `d(i, j) = (TV(h_i, h_j) + |m_i − m_j|) / 2` in [0, 1], `TV` the total-variation distance of
  the L1-normalised colour histograms and `m` the mean disparity as a share of the search range;
- each step picks, among the frames at least `min_spacing_ns` from every frame picked so far, the one
  of the largest `u_i + min_{s picked} d(i, s)` (the first: the largest `u_i`), the earliest on ties.

So the first frame is the most uncertain one, and every next one trades uncertainty against how unlike
the frames already picked it looks; frames of one hovering moment are never picked twice (the spacing),
and a labeller corrects what the model gets wrong on views it has not seen, not the same view N times.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

#: Bins per RGB channel of the colour histogram (4³ = 64 bins: coarse colour, robust to noise).
HISTOGRAM_BINS = 4
#: Width the left view is shrunk to before its histogram is taken (the statistics need no detail).
HISTOGRAM_WIDTH_PX = 160
#: Cut points of neighbouring frames this close (m, camera frame) are taken as the same branch: a drone
#: near a tree moves a few centimetres between frames, branches stand further apart than this.
FLICKER_GATE_M = 0.15


@dataclass(frozen=True)
class FrameStats:
    """What selection knows of one candidate frame.

    - `index`, `timestamp_ns`: the frame's index and capture time (ns) in its source.
    - `colour`: L1-normalised RGB histogram of the left view, `(HISTOGRAM_BINS³,)` float.
    - `near`: mean valid disparity as a share of the disparity search range, 0..1.
    - `confidence`: mean confidence of the frame's cut points, 0..1 (0 without any).
    - `agreement`: IoU of the learned and the structure segmenters' branch pixels, 0..1.
    - `cut_points`: the frame's cut points, `(K, 3)` metres in the camera frame.
    - `flicker`: share of branches that appear or vanish for this frame alone, 0..1 (`with_flicker`).
    """

    index: int
    timestamp_ns: int
    colour: np.ndarray
    near: float
    confidence: float
    agreement: float
    cut_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    flicker: float = 0.0

    @property
    def uncertainty(self) -> float:
        """`((1 − confidence) + (1 − agreement) + flicker) / 3`, 0..1: high when labelling this frame teaches most."""
        return ((1.0 - self.confidence) + (1.0 - self.agreement) + self.flicker) / 3.0

    def distance(self, other: FrameStats) -> float:
        """`(TV(colour) + |Δnear|) / 2`, 0..1: how unlike two frames look."""
        variation = 0.5 * float(np.abs(self.colour - other.colour).sum())
        return (variation + abs(self.near - other.near)) / 2.0


def colour_histogram(left: np.ndarray) -> np.ndarray:
    """L1-normalised `HISTOGRAM_BINS³` RGB histogram of a `uint8 H×W×3` image (shrunk first)."""
    height, width = left.shape[:2]
    scale = min(1.0, HISTOGRAM_WIDTH_PX / width)
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    small = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
    counts = cv2.calcHist([small], [0, 1, 2], None, [HISTOGRAM_BINS] * 3, [0, 256] * 3).reshape(-1)
    return (counts / max(1.0, float(counts.sum()))).astype(np.float64)


def mask_agreement(a: np.ndarray, b: np.ndarray) -> float:
    """IoU of two boolean `H×W` masks; 1 when both are empty (the segmenters agree there is nothing)."""
    union = int((a | b).sum())
    return 1.0 if union == 0 else int((a & b).sum()) / union


def _matched(points: np.ndarray, others: np.ndarray) -> np.ndarray:
    """Which of `points` `(K, 3)` m have one of `others` `(L, 3)` m within `FLICKER_GATE_M`, `(K,)` bool."""
    if len(points) == 0 or len(others) == 0:
        return np.zeros(len(points), dtype=bool)
    gaps = np.linalg.norm(points[:, None, :] - others[None, :, :], axis=2)
    return np.asarray((gaps <= FLICKER_GATE_M).any(axis=1))


def with_flicker(stats: Sequence[FrameStats]) -> list[FrameStats]:
    """`stats` (in time order) with each frame's `flicker` set from its neighbours' cut points (see the module
    docstring): branches neither neighbour sees (appeared, then vanished), and branches both neighbours see
    that this frame missed. The first and last frame, with one neighbour, cannot tell and keep 0."""
    out = list(stats[:1])
    for before, frame, after in zip(stats, stats[1:], stats[2:]):
        points = frame.cut_points
        lonely = int((~(_matched(points, before.cut_points) | _matched(points, after.cut_points))).sum())
        both = before.cut_points[_matched(before.cut_points, after.cut_points)]
        missed = int((~_matched(both, points)).sum())
        total = len(points) + missed
        out.append(replace(frame, flicker=(lonely + missed) / total if total else 0.0))
    return out + ([stats[-1]] if len(stats) > 1 else [])


def select_frames(stats: Sequence[FrameStats], count: int, min_spacing_ns: int) -> list[FrameStats]:
    """Up to `count` of `stats` by the rule of the module docstring, in the order picked (fewer when the
    spacing leaves fewer frames). `count` ≥ 1 and `min_spacing_ns` ≥ 0, else `ValueError`."""
    if count < 1 or min_spacing_ns < 0:
        raise ValueError(f"select {count} frames {min_spacing_ns} ns apart: expected count ≥ 1 and spacing ≥ 0")
    uncertainty = np.array([s.uncertainty for s in stats])
    times = np.array([s.timestamp_ns for s in stats], dtype=np.int64)
    nearest = np.zeros(len(stats))  # distance to the nearest frame picked so far (0 before the first)
    eligible = np.ones(len(stats), dtype=bool)
    picked: list[FrameStats] = []
    while len(picked) < count and eligible.any():
        score = np.where(eligible, uncertainty + nearest, -np.inf)
        best = int(np.argmax(score))  # the first of equal scores: the earliest frame
        chosen = stats[best]
        picked.append(chosen)
        eligible &= np.abs(times - chosen.timestamp_ns) >= max(1, min_spacing_ns)
        distances = np.array([chosen.distance(s) for s in stats])
        nearest = distances if len(picked) == 1 else np.minimum(nearest, distances)
    return picked
