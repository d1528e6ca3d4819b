"""Scoring published results against a flight's truth (`branchrange.offline.flight_score`), on a handmade flight
whose answers are worked out by hand: a right target, a target 8 cm off, no target, a dropped frame, and a
branch entering view at frame 1 first found at frame 4."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
from result_factory import branch, frame_result

from branchrange.config.loader import load_config
from branchrange.core.frame_result import FrameResult, Latency
from branchrange.core.frame_results import result_line, run_header_line
from branchrange.offline.flight import FlightCutPoint, FlightPose, FlightTruth
from branchrange.offline.flight_score import origin_scores, score_results
from branchrange.offline.flight_visibility import DERIVED, FROM_FLIGHT_JSON, CameraView, visible_in_frames
from stereo.cli import build_parser

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from score_flight import recording_view, score_log  # noqa: E402 — a benchmark script, imported from its folder

FPS = 15.0
#: 100 × 80 px, focal 100 px, centred; the daemon's default depth band.
VIEW = CameraView(100.0, 50.0, 40.0, 100, 80, 0.3, 8.0)
#: World cut points (frame 0's camera): A straight ahead; B 1.5 m right (its pixel u = 100 at frame 0: just
#: outside; the camera slides 10 cm right a frame, so B is inside from frame 1); C behind; D beyond 8 m.
CUTS = {1: (0.0, 0.0, 3.0), 2: (1.5, 0.0, 3.0), 3: (0.0, 0.0, -1.0), 4: (0.0, 0.0, 20.0)}


def stamp(position: int) -> int:
    return 1_000_000_000 + round(position * 1e9 / FPS)


def flight(visible: list[list[int]] | None = None, frames: int = 8) -> FlightTruth:
    """The handmade flight: 8 frames at 15 fps, sliding 10 cm right a frame, looking ahead."""
    poses = [
        FlightPose(i, stamp(i), np.eye(3), np.array([0.1 * i, 0.0, 0.0]), None if visible is None else visible[i])
        for i in range(frames)
    ]
    return FlightTruth(poses, [FlightCutPoint(i, np.array(p), 0.01) for i, p in CUTS.items()])


def seen_from(position: int, cut_id: int, offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Cut point `cut_id` in the camera of frame `position`, moved by `offset` (m)."""
    return np.array(CUTS[cut_id]) - [0.1 * position, 0.0, 0.0] + offset


def result(position: int, branches: list, target_id: int | None, publish_ms: float | None = None) -> FrameResult:
    made = frame_result(branches, target_id, index=position, timestamp_ns=stamp(position))
    return made if publish_ms is None else dataclasses.replace(made, latency=Latency(1.0, 2.0, publish_ms))


def published(publish_ms: float | None = None) -> list[FrameResult]:
    """Frame 0 right; 1 a target 8 cm off A; 2 no target; 3 dropped; 4 right, with B found beside it."""
    return [
        result(0, [branch(7, seen_from(0, 1))], 7, publish_ms),
        result(1, [branch(7, seen_from(1, 1, (0.08, 0.0, 0.0)))], 7, publish_ms),
        result(2, [], None, publish_ms),
        result(4, [branch(7, seen_from(4, 1)), branch(8, seen_from(4, 2, (0.0, 0.02, 0.0)))], 7, publish_ms),
    ]


def test_scores_of_a_handmade_flight():
    scores = score_results(published(), flight(), VIEW, 0.5)
    assert scores["visibility"] == DERIVED
    assert (scores["frames_released"], scores["frames_processed"], scores["frames_with_visible_cut"]) == (8, 4, 4)
    assert scores["target_recall"] == 0.75  # targets in frames 0, 1, 4 of the 4 with a visible cut
    assert scores["right_target_rate"] == 0.5  # frame 1's is 8 cm off
    assert scores["false_target_rate"] == pytest.approx(1 / 3, abs=1e-4)
    assert scores["target_error_m"]["median"] == pytest.approx(0.0, abs=1e-9)
    assert scores["target_error_m"]["p90"] == pytest.approx(np.percentile([0.0, 0.0, 0.08], 90), abs=1e-6)
    first = scores["first_result_s"]
    assert (first["branches_in_view"], first["branches_found"]) == (2, 2)  # C behind, D beyond the band: never
    assert first["max"] == pytest.approx(3 / FPS, abs=1e-9)  # B: in view at frame 1, found at frame 4
    assert first["median"] == pytest.approx(1.5 / FPS, abs=1e-9)  # A: found at once
    assert scores["fresh_rate_hz"] == 0.0 and scores["latency_ms"]["p50"] is None  # no latency recorded
    assert scores["keyframe_rate_hz"] is None and scores["target_error_m_by_origin"] is None  # no origin in v1


def test_latency_counts_in_freshness_and_in_the_time_to_a_first_result():
    results = published(publish_ms=120.0)
    results[-1] = dataclasses.replace(results[-1], latency=Latency(1.0, 2.0, 300.0))
    scores = score_results(results, flight(), VIEW, 0.5)
    assert scores["fresh_rate_hz"] == pytest.approx(4 / (8 / FPS), abs=1e-3)
    assert scores["latency_ms"]["max"] == 300.0
    assert scores["first_result_s"]["max"] == pytest.approx(3 / FPS + 0.3, abs=1e-9)  # published 0.3 s later
    assert scores["first_result_s"]["median"] == pytest.approx((0.12 + 3 / FPS + 0.3) / 2, abs=1e-9)
    results[-1] = dataclasses.replace(results[-1], latency=Latency(1.0, 2.0, 700.0))  # stale: sent as no target
    scores = score_results(results, flight(), VIEW, 0.5)
    assert scores["fresh_rate_hz"] == pytest.approx(3 / (8 / FPS), abs=1e-3)
    assert scores["first_result_s"] == {"median": 0.12, "max": 0.12, "branches_in_view": 2, "branches_found": 1}
    assert scores["right_target_rate"] == 0.5  # the target figures count it all the same


def test_recorded_visibility_is_used_when_every_frame_has_it():
    only_a = flight([[1]] * 8)  # the masks say B is hidden (behind a leaf, say) all along
    scores = score_results(published(), only_a, VIEW, 0.5)
    assert scores["visibility"] == FROM_FLIGHT_JSON
    assert scores["first_result_s"]["branches_in_view"] == 1
    far = flight([[1, 4]] * 8)  # D at 20 m is past the depth band even where the masks show it
    assert score_results(published(), far, VIEW, 0.5)["first_result_s"]["branches_in_view"] == 1


def test_results_of_other_frames_are_ignored():
    scores = score_results([*published(), result(50, [branch(7, (0.0, 0.0, 1.0))], 7)], flight(), VIEW, 0.5)
    assert scores["frames_processed"] == 4 and scores["target_recall"] == 0.75


def test_origin_columns_read_each_results_origin():
    origins = ["keyframe", "tracked", "tracked", "keyframe", "tracked"]
    scores = origin_scores(origins, [0.01, 0.02, None, 0.03, 0.005], 1.0)
    assert scores["keyframe_rate_hz"] == 2.0 and scores["tracked_share"] == 0.6 and scores["track_losses"] == 1
    assert scores["target_error_m_by_origin"]["keyframe"]["median"] == pytest.approx(0.02)
    assert scores["target_error_m_by_origin"]["tracked"]["median"] == pytest.approx(0.0125)
    unknown = origin_scores([None, None], [0.01, None], 1.0)
    assert unknown == dict.fromkeys(("keyframe_rate_hz", "tracked_share", "track_losses", "target_error_m_by_origin"))


def test_a_results_log_is_scored_run_by_run(tmp_path: Path):
    log = tmp_path / "results.jsonl"
    cfg = load_config(None)
    with log.open("w", encoding="utf-8") as stream:
        stream.write(run_header_line("daemon", cfg, "replay:flight"))
        stream.writelines(result_line(r) for r in published())
        stream.write(run_header_line("daemon", cfg, "replay:flight"))
        stream.write(result_line(published()[0]))
    runs = score_log(log, flight(), VIEW, 0.5)
    assert [header["kind"] for header, _ in runs if header] == ["daemon", "daemon"]
    assert runs[0][1] == score_results(published(), flight(), VIEW, 0.5)
    assert (runs[1][1]["frames_processed"], runs[1][1]["right_target_rate"]) == (1, 1.0)


def test_derived_visibility_covers_what_a_rendered_flights_masks_show(tmp_path: Path):
    """On a rendered flight, every cut point its masks show is in front and inside the image by the
    recording's calibration (the derived rule sees no occlusion, so it may show more, never less)."""
    out = tmp_path / "rec"
    argv = ["synth-flight", "--out", str(out), "--frames", "4", "--resolution", "320x180", "--seed", "3"]
    args = build_parser("branchrange", "test", ["branchrange.commands.synth_flight"]).parse_args(argv)
    assert args.func(args) == 0
    recorded = FlightTruth.load(out)
    derived = FlightTruth([dataclasses.replace(p, visible_cut_ids=None) for p in recorded.poses], recorded.cut_points)
    view = recording_view(out, 0.3, 8.0)
    assert (view.width, view.height, view.cx, view.cy) == (320, 180, 159.5, 89.5)
    by_masks, rule = visible_in_frames(recorded, view)
    by_geometry, derived_rule = visible_in_frames(derived, view)
    assert (rule, derived_rule) == (FROM_FLIGHT_JSON, DERIVED)
    assert all(shown <= seen for shown, seen in zip(by_masks, by_geometry, strict=True))
    assert sum(map(len, by_masks)) >= 4  # the target at least, in every frame
