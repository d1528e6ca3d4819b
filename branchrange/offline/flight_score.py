"""Scores of the results published over a flight against its truth: what the autopilot was given.

Input: one run's `branchrange/v1` results in publishing order (the daemon's results log read
back, `frame_results.read_runs`), each naming its captured frame (`frame.index`, the recording's
index), and the flight's `flight.json` truth; frames are matched by index. Distances are compared in the
rectified left camera frame of the frame's capture. A point is *right* within `CORRECT_WITHIN_M`
(5 cm, the cut-point confidence's own definition). Which cut points a frame shows:
`flight_visibility.visible_in_frames`. Keys of `score_results`:
- `frames_released`: frames of the flight; `frames_processed`: published results of its frames;
  `frames_with_visible_cut`: those whose frame shows a true cut point;
- `fresh_rate_hz`: results whose capture → publish age (`latency`) ≤ `max_result_age_s`, per
  second of flight; `latency_ms.{p50,p95,max}`: capture → publish over the results that carry it;
- `target_recall`: results with a target / `frames_with_visible_cut` (any target, right or not);
- `right_target_rate`: results whose target lies within 5 cm of a cut point the frame shows /
  `frames_with_visible_cut`;
- `false_target_rate`: targets farther than 5 cm from every true cut point / targets;
- `target_error_m.{median,p90}`: a target to the nearest true cut point, over targets;
- `first_result_s.{median,max}`: per branch, from the capture of the first frame showing its cut point
  to the publishing of the first result (of that frame or a later one) with a cut point within 5 cm
  of it that was fresh on publishing (a stale one goes out as "no target"): the capture-time
  difference plus that result's capture → publish latency when it carries one; `branches_in_view`,
  `branches_found` count the branches it is taken over;
- `keyframe_rate_hz`, `tracked_share`, `track_losses`, `target_error_m_by_origin.{keyframe,tracked}`:
  from a result's `origin` ("keyframe" or "tracked") — keyframes per second of flight, the share of
  results carried forward by tracking, tracked → keyframe hand-backs (a track dropped, or a
  scheduled keyframe: the origin alone does not tell them apart) and the target error of each; all
  None while results have no `origin` (`branchrange/v1` has no such field yet: nothing to count);
- `visibility`: which rule decided the visible cut points.
The target figures count every published result, fresh or not: how good the targets are; how many
arrive in time is `fresh_rate_hz`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from branchrange.core.confidence import CORRECT_WITHIN_M
from branchrange.core.frame_result import FrameResult
from branchrange.offline.flight import FlightTruth
from branchrange.offline.flight_visibility import CameraView, visible_in_frames

ORIGINS = ("keyframe", "tracked")


def percentile(values: Sequence[float], q: float) -> float | None:
    """The `q`-th percentile of `values`, None when there are none."""
    return float(np.percentile(values, q)) if len(values) else None


def spread(values: Sequence[float]) -> dict[str, float | None]:
    """Median and 90th percentile of `values` (None when empty)."""
    return {"median": percentile(values, 50), "p90": percentile(values, 90)}


def rate(count: int, total: int) -> float | None:
    """`count / total` to 4 decimals, None when `total` is 0 (nothing to take the share of)."""
    return round(count / total, 4) if total else None


def flight_duration_s(truth: FlightTruth) -> float:
    """Seconds the flight's frames span, one frame interval (the median) included for the last frame."""
    stamps = np.array([pose.timestamp_ns for pose in truth.poses], dtype=np.float64)
    interval = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.0
    return float(stamps[-1] - stamps[0] + interval) / 1e9


def nearest_m(point: Sequence[float], truths: Sequence[np.ndarray]) -> float:
    """Distance (m) from `point` to the nearest of `truths` (inf when there are none)."""
    return min((float(np.linalg.norm(np.asarray(point) - t)) for t in truths), default=float("inf"))


def frame_positions(truth: FlightTruth) -> dict[int, int]:
    """Frame index → position of its pose in the flight."""
    return {pose.index: position for position, pose in enumerate(truth.poses)}


def publish_age_s(result: FrameResult) -> float | None:
    """Seconds from the frame's capture to the result's publishing, None when the result does not say."""
    age_ms = result.latency.capture_to_publish_ms if result.latency else None
    return None if age_ms is None else age_ms / 1000


def first_results_s(
    results: Sequence[FrameResult], truth: FlightTruth, visible: Sequence[set[int]], max_result_age_s: float
) -> tuple[list[float], int]:
    """Per branch found, seconds from its cut point entering view to its first right, fresh result (module
    docstring), and how many branches entered view."""
    positions = frame_positions(truth)
    entered: dict[int, int] = {}  # cut point id → position of the first frame showing it
    for shown_at, ids in enumerate(visible):
        for cut_id in ids:
            entered.setdefault(cut_id, shown_at)
    found: dict[int, float] = {}
    for result in results:
        position, age_s = positions.get(result.frame.index), publish_age_s(result)
        if position is None or (age_s is not None and age_s > max_result_age_s):
            continue
        in_camera = truth.cut_points_in_camera(position)
        for cut_id, start in entered.items():
            if cut_id in found or position < start:
                continue
            if any(nearest_m(b.cut_point_m, [in_camera[cut_id]]) <= CORRECT_WITHIN_M for b in result.branches):
                captured_s = (truth.poses[position].timestamp_ns - truth.poses[start].timestamp_ns) / 1e9
                found[cut_id] = captured_s + (age_s or 0.0)
    return list(found.values()), len(entered)


def origin_scores(origins: Sequence[str | None], errors: Sequence[float | None], duration_s: float) -> dict[str, Any]:
    """The keyframe/tracked columns from each result's `origin` (None: the result has none) and its target
    error (None: no target); every value None when no result has an origin."""
    if all(origin is None for origin in origins):
        return {
            "keyframe_rate_hz": None,
            "tracked_share": None,
            "track_losses": None,
            "target_error_m_by_origin": None,
        }
    return {
        "keyframe_rate_hz": round(origins.count("keyframe") / duration_s, 3),
        "tracked_share": rate(origins.count("tracked"), len(origins)),
        "track_losses": sum(a == "tracked" and b == "keyframe" for a, b in zip(origins, origins[1:])),
        "target_error_m_by_origin": {
            kind: spread([e for o, e in zip(origins, errors) if o == kind and e is not None]) for kind in ORIGINS
        },
    }


def score_results(
    results: Sequence[FrameResult], truth: FlightTruth, view: CameraView, max_result_age_s: float
) -> dict[str, Any]:
    """The module docstring's scores of one run's results against the flight's truth."""
    positions = frame_positions(truth)
    visible, rule = visible_in_frames(truth, view)
    duration_s = flight_duration_s(truth)
    ours = [result for result in results if result.frame.index in positions]
    with_visible = targets = hits = right = false_targets = 0
    errors: list[float | None] = []
    for result in ours:
        position = positions[result.frame.index]
        in_camera = truth.cut_points_in_camera(position)
        shown = visible[position]
        with_visible += bool(shown)
        target = result.target
        if target is None:
            errors.append(None)
            continue
        error = nearest_m(target.cut_point_m, list(in_camera.values()))
        errors.append(error)
        targets += 1
        false_targets += error > CORRECT_WITHIN_M
        if shown:
            hits += 1
            right += nearest_m(target.cut_point_m, [in_camera[i] for i in shown]) <= CORRECT_WITHIN_M
    ages = [1000 * age for age in map(publish_age_s, ours) if age is not None]
    found_s, in_view = first_results_s(ours, truth, visible, max_result_age_s)
    return {
        "frames_released": len(truth.poses),
        "frames_processed": len(ours),
        "frames_with_visible_cut": with_visible,
        "fresh_rate_hz": round(sum(age <= 1000 * max_result_age_s for age in ages) / duration_s, 3),
        "latency_ms": {"p50": percentile(ages, 50), "p95": percentile(ages, 95), "max": max(ages, default=None)},
        "target_recall": rate(hits, with_visible),
        "right_target_rate": rate(right, with_visible),
        "false_target_rate": rate(false_targets, targets),
        "target_error_m": spread([e for e in errors if e is not None]),
        "first_result_s": {
            "median": percentile(found_s, 50),
            "max": max(found_s, default=None),
            "branches_in_view": in_view,
            "branches_found": len(found_s),
        },
        **origin_scores([getattr(result, "origin", None) for result in ours], errors, duration_s),
        "visibility": rule,
    }
