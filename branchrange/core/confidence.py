"""Confidence that predicts correctness: a monotone map from a raw cut-point confidence to the share of
cut points at that raw value that lie within 5 cm of a true cut point, fitted on held-out scenes.

Why: the raw confidence (segmenter score × fit quality × stereo agreement × evidence) ranks cut points
well but is not a probability — a raw 0.7 can mean 40 % or 95 % correct depending on the segmenter and
the stereo stage. A segmenter that has been measured ships its calibration (`LearnedSegmenter`, in its
model's JSON); the cut-point stage applies it, so "confidence 0.8" means "about 8 in 10 are right".
The fit is isotonic regression (pool adjacent violators): the only assumption is that a higher raw
confidence is never worse.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: a cut point within this distance (m) of a true one is correct (the evaluation's recall radius)
CORRECT_WITHIN_M = 0.05


def cut_point_outcomes(
    estimates: Iterable[tuple[float, Sequence[float]]], true_points: Sequence[Sequence[float]]
) -> list[tuple[float, bool]]:
    """(confidence, correct) of each (confidence, cut point m) estimate: correct when some true cut point
    lies within `CORRECT_WITHIN_M` — the pairs the calibration is fitted on and the reliability tables count."""
    truth = [np.asarray(t, dtype=np.float64) for t in true_points]
    return [
        (float(c), any(float(np.linalg.norm(np.asarray(p, dtype=np.float64) - t)) <= CORRECT_WITHIN_M for t in truth))
        for c, p in estimates
    ]


def visible_length_factor(visible_m: float, scale_m: float) -> float:
    """Factor in [0, 1) for a branch seen `visible_m` metres long (base to tip): L / (L + `scale_m`); 1 for a
    `scale_m` of 0.

    Why: a short piece is more often a fragment — a bark ridge read as a stem, a twig end, a leaf edge — and its
    axis, so the cut point 5 cm from its base, rests on few pixels. With the learned segmenter looking once
    (SGBM, 640×360), ranking by this factor as well (scale 0.1 m) found 41.1 instead of 38.3 % of the branches
    at ≤ 0.5 false cut points a frame on 240 held-out scenes (calibration scenes: 41.9 against 37.5 %); the
    calibration then says what the product means."""
    if scale_m <= 0:
        return 1.0
    visible_m = max(0.0, float(visible_m))
    return visible_m / (visible_m + scale_m)


@dataclass(frozen=True)
class ConfidenceCalibration:
    """Piecewise-linear monotone map: raw confidence `raw` (ascending knots in [0, 1]) → `calibrated`."""

    raw: tuple[float, ...]
    calibrated: tuple[float, ...]

    def __post_init__(self) -> None:
        raw, out = np.asarray(self.raw), np.asarray(self.calibrated)
        if raw.ndim != 1 or raw.shape != out.shape or len(raw) < 1:
            raise ValueError("a confidence calibration needs equally many (≥ 1) raw and calibrated knots")
        if np.any(np.diff(raw) < 0) or np.any(np.diff(out) < 0):
            raise ValueError("confidence calibration knots must be ascending (a monotone map)")
        if raw.min() < 0 or raw.max() > 1 or out.min() < 0 or out.max() > 1:
            raise ValueError("confidence calibration knots must lie in [0, 1]")

    def __call__(self, confidence: float) -> float:
        """The calibrated confidence of a raw one (flat beyond the outer knots)."""
        return float(np.interp(confidence, self.raw, self.calibrated))

    def to_json_dict(self) -> dict[str, list[float]]:
        """`{"raw": [...], "calibrated": [...]}` (rounded to 4 decimals)."""
        return {"raw": [round(x, 4) for x in self.raw], "calibrated": [round(y, 4) for y in self.calibrated]}

    @classmethod
    def from_json_dict(cls, data: dict[str, Any]) -> ConfidenceCalibration:
        """The calibration of `to_json_dict`'s form; ValueError naming what is wrong."""
        try:
            return cls(tuple(float(x) for x in data["raw"]), tuple(float(y) for y in data["calibrated"]))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"confidence calibration: expected 'raw' and 'calibrated' lists ({exc})") from None


def product_calibration(first: ConfidenceCalibration, second: ConfidenceCalibration) -> ConfidenceCalibration:
    """The map c → `first`(c) × `second`(c), at the union of both maps' knots: the probability that two things
    hold, the second measured given the first (a fine-tuned bundle's "on a branch" × "within 5 cm given on a
    branch", `branchrange.learning.depth_factor`). Both are monotone and in [0, 1], so the product is too."""
    knots = np.union1d(first.raw, second.raw)
    product = np.maximum.accumulate([first(float(c)) * second(float(c)) for c in knots])  # rounding kept monotone
    return ConfidenceCalibration(tuple(float(c) for c in knots), tuple(float(p) for p in product))


def fit_calibration(raw: Sequence[float], correct: Sequence[bool], min_count: int = 20) -> ConfidenceCalibration:
    """Isotonic fit of `correct` (0/1) on `raw` confidences; blocks of fewer than `min_count` cut points are
    pooled with their neighbour so that no knot rests on a handful of samples. Knots sit at each block's
    mean raw confidence; each block's share is (right + 1) / (count + 2), never a bare 0 or 1."""
    order = np.argsort(np.asarray(raw, dtype=np.float64), kind="stable")
    x = np.asarray(raw, dtype=np.float64)[order]
    y = np.asarray(correct, dtype=np.float64)[order]
    if len(x) == 0:
        raise ValueError("no cut points to fit a confidence calibration on")
    blocks: list[list[float]] = []  # [sum x, sum y, count]
    for xi, yi in zip(x, y, strict=True):
        blocks.append([xi, yi, 1.0])
        while len(blocks) > 1 and (
            blocks[-2][1] / blocks[-2][2] >= blocks[-1][1] / blocks[-1][2] or blocks[-2][2] < min_count
        ):
            sx, sy, n = blocks.pop()
            blocks[-1] = [blocks[-1][0] + sx, blocks[-1][1] + sy, blocks[-1][2] + n]
    if len(blocks) > 1 and blocks[-1][2] < min_count:
        sx, sy, n = blocks.pop()
        blocks[-1] = [blocks[-1][0] + sx, blocks[-1][1] + sy, blocks[-1][2] + n]
    knots_x = [float(np.clip(b[0] / b[2], 0.0, 1.0)) for b in blocks]
    # Laplace's rule of succession per block: 12 of 12 right is "about 93 %", not a certainty
    knots_y = list(np.maximum.accumulate([(b[1] + 1.0) / (b[2] + 2.0) for b in blocks]))
    return ConfidenceCalibration(tuple(knots_x), tuple(float(v) for v in knots_y))


def share_correct_above(outcomes: Sequence[tuple[float, float]], threshold: float) -> tuple[int, float]:
    """(cut points with confidence ≥ `threshold`, the share of them that are correct) of (confidence, correct)."""
    kept = [ok for c, ok in outcomes if c >= threshold]
    return len(kept), float(np.mean(kept)) if kept else float("nan")


def expected_calibration_error(outcomes: Sequence[tuple[float, bool]], bins: int = 10) -> float:
    """How far confidences are from the share correct: the mean over cut points of |mean confidence − share
    correct| within each of `bins` equal confidence bins (0 for a perfectly honest confidence); NaN without any.
    Unlike the share correct above one threshold it weighs every cut point, the ones an obstacle map keeps too."""
    if not outcomes:
        return float("nan")
    confidence = np.asarray([c for c, _ in outcomes], dtype=np.float64)
    correct = np.asarray([ok for _, ok in outcomes], dtype=np.float64)
    which = np.minimum((confidence * bins).astype(int), bins - 1)
    gap = 0.0
    for b in np.unique(which):
        inside = which == b
        gap += inside.sum() * abs(confidence[inside].mean() - correct[inside].mean())
    return float(gap / len(outcomes))


#: the thresholds the defaults are chosen from: 0.01, 0.02, … 0.99. Why this fine: an isotonic block holds
#: dozens of cut points at one calibrated value, and in steps of 0.05 the step from a block at 0.80 to 0.85
#: dropped a third of the confident cut points (the shipped model on scenes 2861–2980: 0.81 keeps 242 at
#: 90.5 % right, 0.85 only 201 at 91.5 %)
THRESHOLD_STEP = 0.01
_THRESHOLDS = np.round(np.arange(THRESHOLD_STEP, 1.0, THRESHOLD_STEP), 2)


def lowest_reliable_threshold(outcomes: Sequence[tuple[float, float]], share: float = 0.9) -> float | None:
    """The lowest confidence (steps of `THRESHOLD_STEP`) at and above which at least `share` of the cut points
    are correct — the default a target needs; None when no threshold reaches it. Each outcome's correct is
    True/False, or the probability that it is (a fine-tuned bundle's,
    `branchrange.learning.heldout.calibration_table`)."""
    for threshold in _THRESHOLDS:
        count, correct = share_correct_above(outcomes, float(threshold))
        if count and correct >= share:
            return float(threshold)
    return None


def highest_inclusive_threshold(outcomes: Sequence[tuple[float, bool]], keep: float = 0.98) -> float:
    """The highest confidence (steps of `THRESHOLD_STEP`) that still keeps at least `keep` of the correct cut
    points — the default an obstacle needs (a real branch must not be dropped from the map for a shaky estimate)."""
    right = np.asarray([c for c, ok in outcomes if ok], dtype=np.float64)
    best = 0.0
    for threshold in _THRESHOLDS:
        if len(right) and np.mean(right >= threshold) >= keep:
            best = float(threshold)
    return best
