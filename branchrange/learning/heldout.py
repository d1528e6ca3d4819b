"""Scoring a `BranchNet` on a user's held-out labelled frames, and calibrating its confidence on them.

A user's frames have labelled masks but no true cut points, so a cut point is judged against the labels,
as the real pairs are (`benchmarks/segmenter.py`): it is **right** when its pixel lies within
`RIGHT_WITHIN_PX` of a labelled branch, **wrong** anywhere else — on the trunk (a pruner must not cut
there), on background, foliage, posts — and not counted on an `iscrowd` (ignored) region. Unlike the real
pairs, whose hand polygons cover a few branches, a user's corrected labels are taken as complete, so a cut
point on an unlabelled pixel is wrong. What this does not see: how far the cut point is in depth from the
branch (a right pixel with a bad disparity is still right here). So the calibration fitted here, "the cut
point lies on a branch", is multiplied by how often the model's cut points on a branch are within 5 cm in
synthetic scenes (`branchrange.learning.depth_factor`, which says why): a bundle's confidence then means what the
shipped model's does. The bundle's JSON says how it was measured ("measure", and both factors).

Each held-out frame goes through the pipeline as on board in whole-frame mode (its exported disparity and
stereo confidence, untracked, without the right view: branches are not refined on their own pixels), once
per trunk band of `HELDOUT_TRUNK_BANDS`, with the segmenter's raw confidences.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from branchrange.core.confidence import (
    ConfidenceCalibration,
    fit_calibration,
    highest_inclusive_threshold,
    lowest_reliable_threshold,
    product_calibration,
)
from branchrange.learning.coco_labels import LabelledSample
from branchrange.learning.samples import BRANCH, IGNORE

#: a cut point within this many px of a labelled branch pixel is on it (SGBM fattens edges by a pixel or two)
RIGHT_WITHIN_PX = 3
#: labelled branches smaller than this (px) are not counted in recall: the segmenter drops pieces that small
MIN_LABELLED_BRANCH_PX = 12
#: how the network sees the held-out frames: trunk band 40 px (the default), 0 (one look, as on board)
HELDOUT_TRUNK_BANDS = (40, 0)
#: fewer held-out cut points than this give no calibration table (too few to say what a confidence means)
MIN_CALIBRATION_CUT_POINTS = 20


def judged_cut_points(frame: LabelledSample, pixels: Sequence[Sequence[float]]) -> tuple[list[bool | None], set[int]]:
    """Per cut point pixel [u, v]: True on a labelled branch (within `RIGHT_WITHIN_PX`), None on an ignored
    region, False elsewhere; and the ids of the labelled branches some right cut point lies on."""
    return judged_pixels(frame.sample["classes"], frame.sample["instances"], pixels)


def judged_pixels(
    classes: np.ndarray, instances: np.ndarray, pixels: Sequence[Sequence[float]]
) -> tuple[list[bool | None], set[int]]:
    """`judged_cut_points` on a class map `classes` (`uint8 H×W`, `branchrange.learning.samples` classes) and its
    instance ids `instances` (`H×W`): labelled frames and synthetic scenes (`branchrange.learning.depth_factor`)
    are judged alike."""
    height, width = classes.shape
    outcomes: list[bool | None] = []
    found: set[int] = set()
    r = RIGHT_WITHIN_PX
    for u, v in pixels:
        col, row = int(round(u)), int(round(v))
        window = np.s_[max(0, row - r) : min(height, row + r + 1), max(0, col - r) : min(width, col + r + 1)]
        ys, xs = np.mgrid[window]
        near = (ys - row) ** 2 + (xs - col) ** 2 <= r * r
        ids = instances[window][near & (classes[window] == BRANCH)]
        if ids.size:
            outcomes.append(True)
            found.update(int(i) for i in np.unique(ids))
        elif 0 <= row < height and 0 <= col < width and classes[row, col] == IGNORE:
            outcomes.append(None)
        else:
            outcomes.append(False)
    return outcomes, found


def labelled_branches(frame: LabelledSample) -> set[int]:
    """Ids of the frame's labelled branches of at least `MIN_LABELLED_BRANCH_PX` px."""
    ids, areas = np.unique(frame.sample["instances"][frame.sample["classes"] == BRANCH], return_counts=True)
    return {int(i) for i, a in zip(ids, areas, strict=True) if i and a >= MIN_LABELLED_BRANCH_PX}


def heldout_outcomes(
    model: Path, frames: Sequence[LabelledSample], band: int
) -> tuple[list[tuple[float, bool]], dict[str, int]]:
    """(raw confidence, right) of every counted cut point the ONNX `model` gives on `frames` with trunk band
    `band` px, and the counts: frames, cut points, right, on ignored regions, labelled branches, found."""
    from branchrange.core.pipeline import Pipeline, untracked_whole_frame
    from branchrange.core.segmentation.learned import LearnedSegmenter, LearnedSegmenterConfig

    segmenter = LearnedSegmenter(LearnedSegmenterConfig(model=str(model), calibrated=False, trunk_band_px=band))
    outcomes: list[tuple[float, bool]] = []
    counts = {"frames": len(frames), "cut_points": 0, "right": 0, "ignored": 0, "labelled_branches": 0, "found": 0}
    for frame in frames:
        g = frame.geometry
        pipeline = Pipeline(
            untracked_whole_frame(), focal_px=g.focal_px, baseline_m=g.baseline_m, principal_point=(g.cx, g.cy),
            segmenter=segmenter,
        )  # fmt: skip
        result = pipeline.process_disparity(
            frame.sample["left"], frame.sample["disparity"], frame.confidence, backend="sgbm"
        )
        judged, found = judged_cut_points(frame, [b.pixel for b in result.branches])
        outcomes += [(b.confidence, ok) for b, ok in zip(result.branches, judged, strict=True) if ok is not None]
        wanted = labelled_branches(frame)
        counts["cut_points"] += sum(ok is not None for ok in judged)
        counts["right"] += sum(ok is True for ok in judged)
        counts["ignored"] += sum(ok is None for ok in judged)
        counts["labelled_branches"] += len(wanted)
        counts["found"] += len(wanted & found)
    return outcomes, counts


def scores(counts: dict[str, int], iou: dict[str, float]) -> dict[str, Any]:
    """The held-out figures of one model and trunk band: `counts` (`heldout_outcomes`), the pixel IoU per class,
    cut points a frame, the share of them right (precision) and of labelled branches found (recall)."""
    return {
        **{f"iou_{k}": round(v, 4) for k, v in iou.items() if k != "background"},
        **counts,
        "cut_points_per_frame": round(counts["cut_points"] / max(1, counts["frames"]), 3),
        "precision": round(counts["right"] / counts["cut_points"], 4) if counts["cut_points"] else None,
        "recall": round(counts["found"] / counts["labelled_branches"], 4) if counts["labelled_branches"] else None,
    }


def calibration_table(
    outcomes: list[tuple[float, bool]], width: int, band: int, depth: ConfidenceCalibration | None
) -> dict[str, Any] | None:
    """The "confidence_calibrations" table (the shape `learned.calibrations_by_setting` reads, normal light) of
    held-out `outcomes` seen at `width` px with trunk band `band` px: P(on a labelled branch) times `depth`,
    P(within 5 cm | on a branch) (`branchrange.learning.depth_factor`, which says why). None with fewer than
    `MIN_CALIBRATION_CUT_POINTS` cut points, or without a depth factor: "on a branch" alone is not a confidence
    to fly on. Its thresholds count a held-out cut point as right with the depth factor's probability."""
    if len(outcomes) < MIN_CALIBRATION_CUT_POINTS or depth is None:
        return None
    on_branch = fit_calibration([c for c, _ in outcomes], [ok for _, ok in outcomes], min_count=10)
    calibration = product_calibration(on_branch, depth)
    expected = [(calibration(c), ok * depth(c)) for c, ok in outcomes]  # right: on a branch and within 5 cm
    return {
        "network_width": width,
        "trunk_band_px": band,
        "light": "normal",
        **calibration.to_json_dict(),
        "target_min_confidence": lowest_reliable_threshold(expected, 0.9),
        "obstacle_min_confidence": highest_inclusive_threshold([(calibration(c), ok) for c, ok in outcomes], 0.98),
        "measure": f"cut point within {RIGHT_WITHIN_PX} px of a labelled branch (held-out labelled frames) × within "
        "5 cm given on a branch (synthetic calibration scenes, this model)",
        "on_branch": on_branch.to_json_dict(),
        "depth_given_on_branch": depth.to_json_dict(),
        "cut_points": len(outcomes),
        "share_correct": round(float(np.mean([ok for _, ok in outcomes])), 4),
        "share_within_5cm_expected": round(float(np.mean([r for _, r in expected])), 4),
    }


def frame_width(frames: Sequence[LabelledSample]) -> int:
    """The width (px) most of `frames` have: the width their calibration is keyed by."""
    widths, counts = np.unique([f.sample["left"].shape[1] for f in frames], return_counts=True)
    return int(widths[int(np.argmax(counts))])
