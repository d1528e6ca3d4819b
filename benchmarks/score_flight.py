"""Score a results log (`branchrange/v1` JSONL) against a flight recording's `flight.json`, one score per run.

The log is what the daemon writes (`log.results_jsonl`, or `benchmarks/realtime.py --results-jsonl`):
a run header line, then one line per published result naming its captured frame's index. Each
run is scored on its own (`branchrange.offline.flight_score.score_results`: target recall, right
and false target rates, target error, time from a branch entering view to its first result, fresh
rate and latency, the keyframe/tracked columns when results carry an `origin`); a cut point counts
as visible by `branchrange.offline.flight_visibility` (the recording's calibration, and the depth
band `--min-distance-m`..`--max-distance-m` the daemon reports, defaults `[mavlink]`'s).

    .venv/bin/python benchmarks/score_flight.py out/realtime.jsonl out/bench/flight_hd720 --json out/score.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def read_logged_runs(results_path: Path) -> list[tuple[dict[str, Any] | None, list[Any]]]:
    """(run header, `FrameResult`s) of every run of the log at `results_path`, in the log's order;
    `ResultFormatError` names the key of a line that is not a `branchrange/v1` result."""
    from branchrange.core.frame_result import FrameResult
    from branchrange.core.frame_results import read_runs

    return [(header, [FrameResult.from_json_dict(r) for r in records]) for header, records in read_runs(results_path)]


def score_log(
    results_path: Path, truth: Any, view: Any, max_result_age_s: float
) -> list[tuple[dict[str, Any] | None, dict[str, Any]]]:
    """(run header, scores) of every run of the log at `results_path`, in the log's order."""
    from branchrange.offline.flight_score import score_results

    return [
        (header, score_results(results, truth, view, max_result_age_s))
        for header, results in read_logged_runs(results_path)
    ]


def recording_view(recording: Path, min_distance_m: float, max_distance_m: float) -> Any:
    """The `CameraView` of a recording: its calibration, rectified as the pipeline does, and the depth band."""
    from branchrange.offline.flight_visibility import CameraView
    from camera.sources import ReplaySource

    source = ReplaySource(recording, pace="fast")
    try:
        calibration = source.calibration
    finally:
        source.close()
    if calibration is None:
        raise SystemExit(f"{recording}: the recording has no calibration; its pixels cannot be placed")
    return CameraView.of(calibration, min_distance_m, max_distance_m)


def main(argv: list[str] | None = None) -> int:
    from branchrange.config.sections import MavlinkConfig
    from branchrange.offline.flight import FlightTruth

    band = MavlinkConfig()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="results log (JSONL), e.g. realtime.py --results-jsonl")
    parser.add_argument("recording", type=Path, help="the flight recording (recording.json, flight.json)")
    parser.add_argument("--max-result-age-s", type=float, default=band.max_result_age_s)
    parser.add_argument("--min-distance-m", type=float, default=band.min_distance_m)
    parser.add_argument("--max-distance-m", type=float, default=band.max_distance_m)
    parser.add_argument("--json", type=Path, help="write the scores here")
    args = parser.parse_args(argv)
    truth = FlightTruth.load(args.recording)
    view = recording_view(args.recording, args.min_distance_m, args.max_distance_m)
    runs = [
        {"header": header, "scores": scores}
        for header, scores in score_log(args.results, truth, view, args.max_result_age_s)
    ]
    text = json.dumps({"results": str(args.results), "recording": str(args.recording), "runs": runs}, indent=2)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
