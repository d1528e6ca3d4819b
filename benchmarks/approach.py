"""Approach benchmark: rendered approaches flown through the daemon against a simulated autopilot.

For each speed in `--speeds` (m/s) a `branchrange synth-flight` approach from 3 m to 0.8 m with
sway (5 cm, 0.5 Hz) and 1° attitude jitter is rendered once (cached under out/bench/approach/),
plus, with `--hover-s`, a hover at 0.8 m (the camera drifts 1 cm in that time, sway and jitter
as in the approaches). Each flight is replayed through the whole daemon (`fly_daemon` in
tests/autopilot_sim.py: `branchrange.onboard.daemon.Daemon` with deploy/onboard_cpu.toml's settings,
`mavlink.setpoint_enabled = true`, a real `MavlinkRelay`) with frames released at their timestamps,
while `AutopilotSim` (ArduCopter-like MAVLink 2: GUIDED, armed, ATTITUDE + LOCAL_POSITION_NED at
30 Hz) flies the flight's poses and records every message it receives. `--masks truth` gives the
daemon the recording's instance masks, `builtin` drops them so the built-in segmenter decides. The shipped
`[tracking]` noise is the built-in segmenter's; truth-mask flights take the truth masks' own, measured by
`benchmarks/cut_point_noise.py` on other scenes (`--truth-noise`), so that σ is judged on the cut points it
describes.

Reported per flight, all from what the autopilot received (DEBUG_VECT "CUT", SET_POSITION_TARGET_LOCAL_NED)
and the daemon's published results (the results log's lines, with their fused `targets`):
- `switches`: changes of the sent target between points > 10 cm apart (local NED, through the true
  pose at arrival), no-target sends skipped; `switch_events` says when, and between which true cut
  points (the nearest to each side);
- `first_target_s`: first send with a target, seconds after the first frame was released;
- `error_mm` {median, p90, max} and `off_5cm`: each sent target against the nearest true cut point,
  both in the body frame at the moment it arrived (the truth from flight.json, the pose the sim flew);
  `off_target_events`: each send more than 5 cm off, with its range and the target track as the relay had it;
- `border_targets`: sends whose target track's newest cut point lies within 2 % of the image width
  of the image border (the artefact of a branch the border cuts);
- `nearest` (the true cut point nearest to the camera at the last frame) and `approached` (the one
  the flight heads for): the `runs` of results in which its fused track was seen within
  `mavlink.max_result_age_s` and had a confidence ≥ `cutpoints.target_min_confidence` (a track seen once and
  not since keeps its confidence: that is the segmenter not finding the branch again, not a readiness
  delay), each with the seconds from its start until the track was eligible as the target by the results
  log (also `tracking.target_min_observations` consistent cut points); `ready`: every run eligible within
  1 s or over sooner; `ready_delay_s` the longest such wait; when it was first confident, eligible and
  sent as the target (`confident_s`, `eligible_s`, `target_s`, s after the first frame); `held_back` counts
  its confident results that were not eligible (too few consistent observations), and `held_back_series`
  each of them: [s after the first frame, consistent observations, age s, track error mm];
- `setpoint_dev_mm` {median, max}: each setpoint against the standoff point computed by the daemon's
  own `ApproachPlanner` from the *true* cut point of the sent target and the true pose (step limit
  included, speed cap not); `setpoint_dev_free_mm` over setpoints the speed cap did not hold;
- `speed_capped`: share of setpoints (following a setpoint of the previous send) that moved exactly
  `setpoint_max_speed_m_s` × the time since the previous one (within the ms rounding of time_boot_ms);
- `sigma`: the target track's reported covariance against its actual error (local NED) per send:
  `axis` the share whose error along the covariance's largest axis is within its 1-σ (`sigma_m`,
  ideally 68 %); `radius` the share whose whole error is ≤ `sigma_m`, with `radius_expected`, the
  share a Gaussian with the reported covariance would give (3-D, so below 68 %); `sigma_mm` and
  `axis_error_mm`, the medians of that σ and of the error along its axis (table: `σ mm`, `e∥ mm`). The
  target is judged on `axis` pooled over every flight's sends per mask source (`pooled_coverage`): one
  flight's sends follow mostly one track, whose error persists, so its own share is near 0 or 1 — pool
  scenes with `--seed` runs and `--pool`;
- `release_lag_ms` {median, max}: the daemon's arrival stamp of each frame after its release on the
  simulator's clock (frames are decoded into memory first, as a camera delivers raw frames; a large
  lag would mean the harness, not the daemon, fell behind);
- `latency_ms` by 0.5 m band of the true range to the approach's target cut point at capture:
  p50/p95 of capture (the daemon's arrival stamp) → the first DEBUG_VECT at the autopilot after
  the result was published; `released` frames in the band, `sent` results, `late` ones older than
  `mavlink.max_result_age_s` at the send (frames the daemon dropped are `released − sent`).
Timings depend on the machine's load (it is named in the table); nothing is downloaded.

    .venv/bin/python benchmarks/approach.py --quick                       # 640x360, 0.5 m/s, truth masks
    .venv/bin/python benchmarks/approach.py --json benchmarks/approach.json  # HD720, 0.3/0.5/0.8 m/s, both
    .venv/bin/python benchmarks/approach.py --pool benchmarks/approach.json out/seed3.json  # runs as one
"""

from __future__ import annotations

import argparse
import bisect
import dataclasses
import json
import math
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "benchmarks")]

from autopilot_sim import DaemonFlight, SimPose, fly_daemon  # noqa: E402
from machine import cpu_name  # noqa: E402

from branchrange.config.loader import Config, load_config, parse_override  # noqa: E402
from branchrange.config.sections import MavlinkConfig, TrackingConfig  # noqa: E402
from branchrange.core.frame_result import FrameResult, WorldTrack  # noqa: E402
from branchrange.onboard.mavlink import CameraMount  # noqa: E402

DEPLOY_CONFIG = ROOT / "deploy" / "onboard_cpu.toml"
CACHE = ROOT / "out" / "bench" / "approach"
START_NED_M = (0.0, 0.0, -2.0)
HEADING_DEG = 20.0
SWAY_M, JITTER_DEG = 0.05, 1.0
START_M, END_M = 3.0, 0.8
#: Hover drift over the whole hover (synth-flight needs start > end), metres.
HOVER_DRIFT_M = 0.01
FPS = 15.0
#: The issue's targets.
OFF_TARGET_M = 0.05
SWITCH_APART_M = 0.10
MAX_SWITCHES = 1
READY_WITHIN_S = 1.0
COVERAGE_RANGE = (0.58, 0.78)
LATENCY_P95_MS = 250.0
#: Range bands (m) of the latency table, far to near; the outer bands are open-ended.
BAND_EDGES_M = (3.0, 2.5, 2.0, 1.5, 1.0, 0.8)
#: A target whose cut point pixel lies this share of the image width from the border is a border target.
BORDER_SHARE = 0.02
#: time_boot_ms is whole milliseconds: a step's time is known to ±1 ms at each end.
CAP_TIME_TOLERANCE_S = 0.0015
#: SET_POSITION_TARGET_LOCAL_NED positions are float32.
CAP_LENGTH_TOLERANCE_M = 1e-5
#: cut_point_noise.py's report: the per-view noise of truth masks (see `truth_mask_noise`)
TRUTH_NOISE_FILE = ROOT / "benchmarks" / "results" / "cut_point_noise.json"
#: Samples per send for the Gaussian share inside the 1-σ radius.
RADIUS_SAMPLES = 4000


# --- scoring: pure functions of what was received (tests/test_approach_benchmark.py) ---


def switch_indices(targets_ned: Sequence[np.ndarray | None], apart_m: float = SWITCH_APART_M) -> list[int]:
    """Positions in `targets_ned` (sent targets, m, (3,) each) where the target changed to a point more than
    `apart_m` from the previous target; None (no target) is skipped, so a gap then the same branch is no switch."""
    switches, previous = [], None
    for i, point in enumerate(targets_ned):
        if point is None:
            continue
        if previous is not None and float(np.linalg.norm(point - previous)) > apart_m:
            switches.append(i)
        previous = point
    return switches


def sigma_coverage(errors_m: np.ndarray, covariances_m2: np.ndarray, seed: int = 0) -> dict[str, float | None]:
    """How often the reported 1-σ covers the actual error; `errors_m` (N, 3), `covariances_m2` (N, 3, 3).

    `axis`: share with |error · u| ≤ σ, u the largest eigenvector, σ its root (a calibrated covariance: 68.3 %);
    `radius`: share with |error| ≤ σ; `radius_expected`: the share a Gaussian with each covariance gives;
    `sigma_mm`, `axis_error_mm`: the medians of σ and of |error · u| (mm) — how far from calibrated, and which way."""
    if len(errors_m) == 0:
        return {
            "axis": None,
            "radius": None,
            "radius_expected": None,
            "sigma_mm": None,
            "axis_error_mm": None,
            "sends": 0,
        }
    rng = np.random.default_rng(seed)
    axis, radius, expected, sigmas, axis_errors = [], [], [], [], []
    for error, covariance in zip(errors_m, covariances_m2):
        values, vectors = np.linalg.eigh(covariance)
        sigma = math.sqrt(max(float(values[-1]), 0.0))
        sigmas.append(sigma)
        axis_errors.append(abs(float(error @ vectors[:, -1])))
        axis.append(axis_errors[-1] <= sigma)
        radius.append(float(np.linalg.norm(error)) <= sigma)
        samples = rng.multivariate_normal(np.zeros(3), covariance, RADIUS_SAMPLES)
        expected.append(float(np.mean(np.linalg.norm(samples, axis=1) <= sigma)))
    return {
        "axis": round(float(np.mean(axis)), 3),
        "radius": round(float(np.mean(radius)), 3),
        "radius_expected": round(float(np.mean(expected)), 3),
        "sigma_mm": round(1000 * float(np.median(sigmas)), 1),
        "axis_error_mm": round(1000 * float(np.median(axis_errors)), 1),
        "sends": len(axis),
    }


def band_of(range_m: float, edges_m: Sequence[float] = BAND_EDGES_M) -> int:
    """Index of the band (`edges_m` far to near) holding `range_m`; beyond the first edge → 0, below the last → last."""
    for i, near_edge in enumerate(edges_m[1:-1]):
        if range_m >= near_edge:
            return i
    return len(edges_m) - 2


def band_label(index: int, edges_m: Sequence[float] = BAND_EDGES_M) -> str:
    """`"3.0–2.5"` for band `index`."""
    return f"{edges_m[index]:.1f}–{edges_m[index + 1]:.1f}"


def speed_capped(steps: Sequence[tuple[float, float]], max_speed_m_s: float) -> list[bool]:
    """Per (dt s, step m) between consecutive setpoints: whether the speed cap held it (step = speed × dt,
    within the ms rounding of the timestamps); a free step is shorter."""
    return [
        abs(step - max_speed_m_s * dt) <= max_speed_m_s * CAP_TIME_TOLERANCE_S + CAP_LENGTH_TOLERANCE_M
        for dt, step in steps
    ]


def stats_mm(values_m: Sequence[float]) -> dict[str, float | None]:
    """Median, p90 and max of metres, in millimetres (None when empty)."""
    if not values_m:
        return {"median": None, "p90": None, "max": None}
    array = 1000 * np.asarray(values_m, dtype=np.float64)
    return {
        "median": round(float(np.median(array)), 1),
        "p90": round(float(np.percentile(array, 90)), 1),
        "max": round(float(array.max()), 1),
    }


def latency_bands(samples: Sequence[tuple[float, float | None]], max_age_s: float) -> list[dict[str, Any]]:
    """Per range band: (range m, capture → send s or None when never sent) → released, sent, late, p50/p95 ms."""
    bands: list[dict[str, Any]] = []
    for index in range(len(BAND_EDGES_M) - 1):
        latencies = [1000 * s for r, s in samples if band_of(r) == index and s is not None]
        released = sum(band_of(r) == index for r, _ in samples)
        bands.append(
            {
                "band_m": band_label(index),
                "released": released,
                "sent": len(latencies),
                "late": sum(ms > 1000 * max_age_s for ms in latencies),
                "p50_ms": round(float(np.percentile(latencies, 50)), 1) if latencies else None,
                "p95_ms": round(float(np.percentile(latencies, 95)), 1) if latencies else None,
            }
        )
    return bands


# --- flights ---


def render_flight(resolution: str, speed_m_s: float | None, hover_s: float, seed: int) -> Path:
    """The cached `branchrange synth-flight` recording of an approach at `speed_m_s`, or of a hover of
    `hover_s` seconds at `END_M` (speed None); rendered once."""
    from branchrange.cli import main as branchrange_main

    name = f"{resolution}_v{speed_m_s:g}_seed{seed}" if speed_m_s else f"{resolution}_hover{hover_s:g}s_seed{seed}"
    out = CACHE / name
    if (out / "flight.json").exists() and (out / "recording.json").exists():
        return out
    path = ["--speed", str(speed_m_s), "--start-m", str(START_M)]
    if speed_m_s is None:
        frames = max(2, round(hover_s * FPS))
        path = ["--frames", str(frames), "--start-m", str(END_M + HOVER_DRIFT_M)]
    arguments = ["synth-flight", "--out", str(out), "--resolution", resolution, "--fps", str(FPS), *path]
    arguments += ["--end-m", str(END_M), "--sway-m", str(SWAY_M), "--jitter-deg", str(JITTER_DEG)]
    print(f"rendering {out} (once) ...", file=sys.stderr)
    code = branchrange_main([*arguments, "--seed", str(seed), "--overwrite"])
    if code != 0:
        raise SystemExit(f"synth-flight {' '.join(arguments)} failed with exit code {code}")
    return out


def approach_target_id(directory: Path) -> int:
    """The cut point id the rendered flight approaches (`synth-flight` notes it in recording.json's source)."""
    source = json.loads((directory / "recording.json").read_text(encoding="utf-8")).get("source", "")
    found = re.search(r"target (\d+)", source)
    if found is None:
        raise SystemExit(f"{directory}/recording.json: source is {source!r}; expected `branchrange synth-flight`'s")
    return int(found.group(1))


def daemon_config(directory: Path, width: int, extra: Sequence[str] = ()) -> Config:
    """deploy/onboard_cpu.toml for the recording: replay source, setpoints on, no API; max_disp scaled to `width`;
    then the `extra` `section.key=value` overrides (`--set`)."""
    max_disp = max(32, round(128 * width / 1280 / 16) * 16)  # 128 px at HD720 reaches the same 0.32 m
    overrides = [
        f'camera.source="replay:{directory}"',
        'camera.calibration=""',
        f"stereo.max_disp={max_disp}",
        "mavlink.setpoint_enabled=true",
        "api.enabled=false",
        'log.results_jsonl=""',
        "log.status_interval_s=3600.0",
        *extra,
    ]
    return load_config(DEPLOY_CONFIG, [parse_override(item) for item in overrides])


# --- scoring a flight ---


@dataclasses.dataclass(frozen=True)
class Send:
    """One frame set the autopilot received: arrival (monotonic s), the relay's time_boot_ms, and the target
    in local NED through the true pose at arrival (None: "no target")."""

    at: float
    time_boot_ms: int
    target_ned_m: np.ndarray | None


def body_to_ned(pose: SimPose, body_m: np.ndarray) -> np.ndarray:
    """Local NED metres (3,) of a body FRD point (3,)."""
    return pose.rotation @ np.asarray(body_m, dtype=np.float64) + pose.position_m


def received_sends(flight: DaemonFlight) -> list[Send]:
    """Every DEBUG_VECT "CUT" the autopilot received, in arrival order."""
    sends = []
    for r in sorted(flight.sim.of_type("DEBUG_VECT"), key=lambda r: r.at):
        body = np.array([r.msg.x, r.msg.y, r.msg.z], dtype=np.float64)
        target = None if np.isnan(body).any() else body_to_ned(flight.sim.pose_at(r.at), body)
        sends.append(Send(r.at, r.msg.time_usec // 1000, target))
    return sends


class ResultsTimeline:
    """The daemon's published results by publish time (monotonic s), to find the newest before a send."""

    def __init__(self, flight: DaemonFlight):
        entries = sorted(
            (flight.publications[result.frame.index][1], result)
            for _, result in flight.published
            if result.frame.index in flight.publications
        )
        self.times = [t for t, _ in entries]
        self.results: list[FrameResult] = [r for _, r in entries]

    def newest(self, at: float) -> int | None:
        """Index of the newest result published at or before `at`, or None."""
        i = bisect.bisect_right(self.times, at) - 1
        return i if i >= 0 else None

    def target_track(self, at: float) -> tuple[int, WorldTrack] | None:
        """(result index, the fused target track) the relay had at `at`, or None."""
        i = self.newest(at)
        targets = None if i is None else self.results[i].targets
        if targets is None or targets.target_track_id is None:
            return None
        track = next((t for t in targets.tracks if t.id == targets.target_track_id), None)
        return None if track is None else (i, track)

    def pixel_of(self, index: int, branch_id: int) -> tuple[float, float] | None:
        """The cut point pixel of `branch_id` in the newest result up to `index` that holds it."""
        for result in reversed(self.results[: index + 1]):
            branch = next((b for b in result.branches if b.id == branch_id), None)
            if branch is not None:
                return branch.pixel
        return None


def nearest_cut(point_m: np.ndarray, cuts_ned: dict[int, np.ndarray]) -> tuple[int, float]:
    """(id, distance m) of the true cut point nearest to a NED point."""
    cut_id = min(cuts_ned, key=lambda i: float(np.linalg.norm(point_m - cuts_ned[i])))
    return cut_id, float(np.linalg.norm(point_m - cuts_ned[cut_id]))


def is_of(point_m: np.ndarray, cut_id: int, cuts_ned: dict[int, np.ndarray]) -> bool:
    """Whether a NED point (3,) m stands for true cut point `cut_id`: it is the nearest, within `SWITCH_APART_M`."""
    nearest, distance = nearest_cut(point_m, cuts_ned)
    return nearest == cut_id and distance <= SWITCH_APART_M


def switch_events(flight: DaemonFlight, sends: list[Send]) -> list[dict[str, Any]]:
    """Each switch of the sent target: seconds after the first frame, and the true cut points (nearest) it
    went from and to, with their distance apart (m)."""
    cuts = flight.cuts_ned()
    points = [s.target_ned_m for s in sends]
    events = []
    for i in switch_indices(points):
        before = next(p for p in reversed(points[:i]) if p is not None)
        after = points[i]
        assert after is not None  # a switch is always to a target
        events.append(
            {
                "t_s": round(sends[i].at - flight.sim.start, 3),
                "from_cut": nearest_cut(before, cuts)[0],
                "to_cut": nearest_cut(after, cuts)[0],
                "apart_m": round(float(np.linalg.norm(after - before)), 3),
            }
        )
    return events


def is_border(pixel: tuple[float, float], width: int, height: int) -> bool:
    """Whether a pixel (u, v) lies within `BORDER_SHARE` of the width from the image border."""
    margin = BORDER_SHARE * width
    u, v = pixel
    return u < margin or v < margin or u > width - 1 - margin or v > height - 1 - margin


def border_targets(sends: list[Send], timeline: ResultsTimeline) -> int:
    """Sends whose target track's newest cut point pixel lies at the image border."""
    count = 0
    for send in sends:
        found = timeline.target_track(send.at) if send.target_ned_m is not None else None
        if found is None:
            continue
        index, track = found
        pixel = timeline.pixel_of(index, track.branch_id)
        frame = timeline.results[index].frame
        count += pixel is not None and is_border(pixel, frame.width, frame.height)
    return count


def off_target_events(
    flight: DaemonFlight, sends: list[Send], timeline: ResultsTimeline, cuts_ned: dict[int, np.ndarray]
) -> list[dict[str, Any]]:
    """Each send whose target lies more than `OFF_TARGET_M` from every true cut point: when (s after the first
    frame), how far off (mm), the range from the vehicle to that cut point (m), and the target track as the relay
    had it (its age, observations, consistent ones, views, confidence, σ) — what made a wrong target go out."""
    events = []
    for send in sends:
        if send.target_ned_m is None:
            continue
        cut_id, off = nearest_cut(send.target_ned_m, cuts_ned)
        if off <= OFF_TARGET_M:
            continue
        found = timeline.target_track(send.at)
        track = None if found is None else found[1]
        pose = flight.sim.pose_at(send.at)
        events.append(
            {
                "at_s": round(send.at - flight.sim.start, 3),
                "off_mm": round(1000 * off, 1),
                "cut_id": cut_id,
                "range_m": round(float(np.linalg.norm(cuts_ned[cut_id] - pose.position_m)), 3),
                "track": None
                if track is None
                else {
                    k: getattr(track, k)
                    for k in ("age_s", "observations", "consistent_observations", "views", "confidence", "sigma_m")
                },
            }
        )
    return events


def sigma_of_sends(sends: list[Send], timeline: ResultsTimeline, cuts_ned: dict[int, np.ndarray]) -> dict[str, Any]:
    """`sigma_coverage` of the target track at every send with a target (actual error against the nearest cut)."""
    errors, covariances = [], []
    for send in sends:
        found = timeline.target_track(send.at) if send.target_ned_m is not None else None
        if found is None:
            continue
        position = np.asarray(found[1].ned_m, dtype=np.float64)
        cut_id, _ = nearest_cut(position, cuts_ned)
        errors.append(position - cuts_ned[cut_id])
        covariances.append(np.asarray(found[1].covariance_m2, dtype=np.float64))
    return sigma_coverage(np.array(errors).reshape(-1, 3), np.array(covariances).reshape(-1, 3, 3))


def confident_runs(samples: Sequence[tuple[float, bool, bool]], end_s: float) -> list[dict[str, float | None]]:
    """Runs of consecutive results in which a branch's track was confident, from (time s, confident, eligible)
    per result in time order: each run's `start_s`, `end_s` (the first result after it that is not
    confident, else `end_s`, the flight's end) and `eligible_after_s`, seconds from its start to its first
    eligible result (None: never eligible in the run)."""
    runs: list[dict[str, float | None]] = []
    current: dict[str, float | None] | None = None
    for t, confident, eligible in samples:
        if not confident:
            if current is not None:
                current["end_s"], current = t, None
            continue
        if current is None:
            current = {"start_s": t, "end_s": end_s, "eligible_after_s": None}
            runs.append(current)
        if eligible and current["eligible_after_s"] is None:
            current["eligible_after_s"] = round(t - float(current["start_s"] or 0.0), 3)
    return runs


def ready_in_time(runs: list[dict[str, float | None]], within_s: float = READY_WITHIN_S) -> bool:
    """Whether every confident run became eligible within `within_s` of its start, or ended before it could."""
    for run in runs:
        after = run["eligible_after_s"]
        lasted = float(run["end_s"] or 0.0) - float(run["start_s"] or 0.0)
        if (after is None and lasted >= within_s) or (after is not None and after > within_s):
            return False
    return True


def readiness(
    flight: DaemonFlight, sends: list[Send], timeline: ResultsTimeline, cut_id: int, cfg: Config
) -> dict[str, Any]:
    """The fused track of true cut point `cut_id` (`is_of`) result by result: `runs` of results in which its
    confidence was ≥ `cutpoints.target_min_confidence` (`confident_runs`), eligible meaning a target by the
    results log (also `tracking.target_min_observations` consistent cut points, captured within
    `mavlink.max_result_age_s`); `ready` whether each run became eligible within 1 s or ended sooner; and
    when it first was confident, eligible and sent as the target (s after the first frame, None: never)."""
    cuts = flight.cuts_ned()
    samples = []
    held_back_series: list[list[float]] = []  # [t s, consistent observations, age s, track error mm] of each
    for t, result in zip(timeline.times, timeline.results):
        tracks = [
            tr for tr in (result.targets.tracks if result.targets else ()) if is_of(np.asarray(tr.ned_m), cut_id, cuts)
        ]
        # confident now: seen within the age a target may have, and confident (a track seen once and not since
        # keeps its confidence but is not a branch in view: that is a detection gap, not a readiness delay)
        fresh = [tr for tr in tracks if tr.age_s <= cfg.mavlink.max_result_age_s]
        confident = [tr for tr in fresh if tr.confidence >= cfg.cutpoints.target_min_confidence]
        eligible = any(tr.consistent_observations >= cfg.tracking.target_min_observations for tr in confident)
        if confident and not eligible:
            track = confident[0]
            off_mm = 1000 * float(np.linalg.norm(np.asarray(track.ned_m) - cuts[cut_id]))
            held_back_series.append(
                [round(t - flight.sim.start, 3), track.consistent_observations, round(track.age_s, 3), round(off_mm, 1)]
            )
        samples.append((round(t - flight.sim.start, 3), bool(confident), eligible))
    end_s = round(timeline.times[-1] - flight.sim.start, 3) if timeline.times else 0.0
    runs = confident_runs(samples, end_s)
    target = next(
        (s.at - flight.sim.start for s in sends if s.target_ned_m is not None and is_of(s.target_ned_m, cut_id, cuts)),
        None,
    )
    delays = [float(r["eligible_after_s"]) for r in runs if r["eligible_after_s"] is not None]
    return {
        "cut_id": cut_id,
        "confident_s": next((t for t, c, _ in samples if c), None),
        "eligible_s": next((t for t, _, e in samples if e), None),
        "target_s": None if target is None else round(target, 3),
        "ready_delay_s": max(delays) if delays else None,
        "ready": ready_in_time(runs),
        "runs": runs,
        "held_back": len(held_back_series),
        "held_back_series": held_back_series,
    }


def nearest_at_arrival(flight: DaemonFlight) -> int:
    """The true cut point nearest to the camera at the last frame, among those the frame shows."""
    in_camera = flight.truth.cut_points_in_camera(len(flight.truth.poses) - 1)
    candidates = flight.truth.poses[-1].visible_cut_ids or list(in_camera)
    return min(candidates, key=lambda i: float(np.linalg.norm(in_camera[i])))


def true_standoff(cfg: MavlinkConfig, tracking: TrackingConfig, cut_ned: np.ndarray, pose: SimPose, t: float):
    """The standoff point (3,) NED m that the daemon's `ApproachPlanner` computes for a track exactly at the
    true cut point, from the true pose, with its step limit and without its speed cap."""
    from branchrange.onboard.mavlink.approach import ApproachPlanner
    from branchrange.onboard.mavlink.connection import PeerHeartbeat
    from branchrange.onboard.mavlink.vehicle_state import Pose
    from branchrange.onboard.mavlink.world_tracks import Measurement, Track

    planner = ApproachPlanner(dataclasses.replace(cfg, setpoint_min_observations=1, setpoint_min_confidence=0.0))
    track = Track.start(0, Measurement(0, cut_ned, np.eye(3) * 1e-6, 1.0, pose.position_m), t, tracking)
    peer = PeerHeartbeat(1, 1, 2, 3, 128 | 1, 4, t)  # ArduCopter, armed (SAFETY_ARMED | CUSTOM_MODE), GUIDED
    setpoint = planner.setpoint(track, Pose(t, pose.rotation, pose.position_m), peer, t)
    assert setpoint is not None, "a track exactly at the cut point is always ready"
    return setpoint[0]


def setpoint_scores(flight: DaemonFlight, sends: list[Send], cfg: Config) -> dict[str, Any]:
    """Setpoint deviation from the true standoff point and the share held by the speed cap."""
    cuts = flight.cuts_ned()
    by_boot = {s.time_boot_ms: s for s in sends}
    boots = sorted(by_boot)
    setpoints = sorted(flight.sim.of_type("SET_POSITION_TARGET_LOCAL_NED"), key=lambda r: r.msg.time_boot_ms)
    sent_at = {r.msg.time_boot_ms: np.array([r.msg.x, r.msg.y, r.msg.z], dtype=np.float64) for r in setpoints}
    deviations, free, steps = [], [], []
    for r in setpoints:
        boot, point = r.msg.time_boot_ms, sent_at[r.msg.time_boot_ms]
        i = bisect.bisect_left(boots, boot)
        previous_boot = boots[i - 1] if i > 0 else None
        capped = False
        if previous_boot is not None and previous_boot in sent_at:
            dt, step = (boot - previous_boot) / 1000, float(np.linalg.norm(point - sent_at[previous_boot]))
            steps.append((dt, step))
            capped = speed_capped([(dt, step)], cfg.mavlink.setpoint_max_speed_m_s)[0]
        send = by_boot.get(boot)
        if send is None or send.target_ned_m is None:
            continue
        cut_id, _ = nearest_cut(send.target_ned_m, cuts)
        goal = true_standoff(cfg.mavlink, cfg.tracking, cuts[cut_id], flight.sim.pose_at(r.at), r.at)
        deviations.append(float(np.linalg.norm(point - goal)))
        if not capped:
            free.append(float(np.linalg.norm(point - goal)))
    capped_flags = speed_capped(steps, cfg.mavlink.setpoint_max_speed_m_s)
    return {
        "setpoints": len(setpoints),
        "setpoint_dev_mm": stats_mm(deviations),
        "setpoint_dev_free_mm": stats_mm(free),
        "speed_capped": round(float(np.mean(capped_flags)), 3) if capped_flags else None,
    }


def capture_to_send(flight: DaemonFlight, sends: list[Send], target_id: int) -> list[tuple[float, float | None]]:
    """Per released frame: (true range m to the approach's target at capture, capture → first send after its
    publication s, None when the daemon dropped it)."""
    arrivals = [s.at for s in sends]
    samples: list[tuple[float, float | None]] = []
    for position, pose in enumerate(flight.truth.poses):
        range_m = float(np.linalg.norm(flight.truth.cut_points_in_camera(position)[target_id]))
        times = flight.publications.get(pose.index)
        i = None if times is None else bisect.bisect_left(arrivals, times[1])
        latency = None if times is None or i is None or i == len(arrivals) else arrivals[i] - times[0]
        samples.append((range_m, latency))
    return samples


def release_lag_ms(flight: DaemonFlight) -> dict[str, float | None]:
    """How late (ms, median and max) the daemon stamped each published frame's arrival after its release time
    on the simulator's clock: the benchmark's own check that the camera kept time (the sim flies the pose of
    a frame's timestamp; a frame stamped later would be fused with a newer pose)."""
    first_ns = flight.truth.poses[0].timestamp_ns
    stamps = {pose.index: (pose.timestamp_ns - first_ns) / 1e9 for pose in flight.truth.poses}
    lags = [
        1000 * (captured - flight.sim.start - stamps[index])
        for index, (captured, _) in flight.publications.items()
        if index in stamps
    ]
    if not lags:
        return {"median": None, "max": None}
    return {"median": round(float(np.median(lags)), 1), "max": round(float(max(lags)), 1)}


def score_flight(flight: DaemonFlight, cfg: Config, target_id: int) -> dict[str, Any]:
    """Every metric of the module docstring for one flight."""
    sends = received_sends(flight)
    timeline = ResultsTimeline(flight)
    cuts = flight.cuts_ned()
    targets = [s for s in sends if s.target_ned_m is not None]
    errors = [nearest_cut(s.target_ned_m, cuts)[1] for s in targets if s.target_ned_m is not None]
    return {
        "frames_released": len(flight.truth.poses),
        "counters": flight.counters,
        "release_lag_ms": release_lag_ms(flight),
        "sends": len(sends),
        "target_sends": len(targets),
        "switches": len(switch_indices([s.target_ned_m for s in sends])),
        "switch_events": switch_events(flight, sends),
        "first_target_s": round(targets[0].at - flight.sim.start, 3) if targets else None,
        "error_mm": stats_mm(errors),
        "off_5cm": sum(e > OFF_TARGET_M for e in errors),
        "off_target_events": off_target_events(flight, sends, timeline, cuts),
        "border_targets": border_targets(sends, timeline),
        "nearest": readiness(flight, sends, timeline, nearest_at_arrival(flight), cfg),
        "approached": readiness(flight, sends, timeline, target_id, cfg),
        **setpoint_scores(flight, sends, cfg),
        "sigma": sigma_of_sends(sends, timeline, cuts),
        "latency_ms": latency_bands(capture_to_send(flight, sends, target_id), cfg.mavlink.max_result_age_s),
    }


def truth_mask_noise(path: Path | None) -> list[str]:
    """`[tracking]` overrides for truth-mask flights: the per-view noise `benchmarks/cut_point_noise.py` measured
    for truth masks (its "all" row, on other scenes than these) — the shipped values are the built-in segmenter's,
    and a σ is honest only for the cut points it is measured on. [] without a file (or `path` None)."""
    if path is None or not path.is_file():
        return []
    rows = [r for r in json.loads(path.read_text())["rows"] if r["flight"] == "all" and r["masks"] == "truth"]
    if not rows:
        return []
    keys = ("disparity_sigma_px", "lateral_sigma_px", "bias_share")
    return [f"tracking.{k}={rows[0][k]:.3g}" for k in keys if rows[0].get(k) is not None]


def run_flight(directory: Path, masks: str, width: int, extra: Sequence[str] = ()) -> dict[str, Any]:
    """Fly one recording through the daemon with `masks` ('truth' or 'builtin') and score it."""
    cfg = daemon_config(directory, width, extra)
    mount = CameraMount.from_rpy(cfg.camera.mount_rpy_deg, cfg.camera.mount_xyz_m)
    flight = fly_daemon(
        directory,
        cfg,
        mount,
        start_ned_m=START_NED_M,
        heading_deg=HEADING_DEG,
        ignore_masks=masks != "truth",
    )
    return score_flight(flight, cfg, approach_target_id(directory))


# --- report ---


def pooled_coverage(rows: list[dict[str, Any]]) -> dict[str, float | None]:
    """Per mask source, the share of all its flights' sends whose error along σ's axis is within σ (each flight's
    `sigma.axis` weighted by its sends). One flight's sends mostly follow one track whose error persists from
    send to send, so its own share is nearly 0 or 1 whatever the calibration: σ is judged over many tracks."""
    pooled: dict[str, float | None] = {}
    for masks in dict.fromkeys(r["masks"] for r in rows):
        judged = [r["sigma"] for r in rows if r["masks"] == masks and r["sigma"]["axis"] is not None]
        sends = sum(s["sends"] for s in judged)
        pooled[masks] = round(sum(s["axis"] * s["sends"] for s in judged) / sends, 3) if sends else None
    return pooled


def verdicts(rows: list[dict[str, Any]]) -> dict[str, bool]:
    """The issue's targets over every flight (the hover included)."""
    approaches = [r for r in rows if r["speed_m_s"]]
    coverage = list(pooled_coverage(rows).values())
    p95 = [b["p95_ms"] for r in approaches for b in r["latency_ms"] if b["released"]]
    return {
        "no target > 5 cm off": all(r["off_5cm"] == 0 for r in rows),
        "no border target": all(r["border_targets"] == 0 for r in rows),
        "≤ 1 switch per approach": all(r["switches"] <= MAX_SWITCHES for r in approaches),
        "nearest ready within 1 s of its confidence": all(r["nearest"]["ready"] for r in approaches),
        "1-σ covers 68 ± 10 % (pooled per masks)": bool(coverage)
        and all(c is not None and COVERAGE_RANGE[0] <= c <= COVERAGE_RANGE[1] for c in coverage),
        "capture → send p95 ≤ 250 ms per band": bool(p95) and all(v is not None and v <= LATENCY_P95_MS for v in p95),
    }


def fmt(value: Any, digits: int = 0) -> str:
    """A number for the table, `—` for None."""
    return "—" if value is None else f"{value:.{digits}f}"


def flight_name(row: dict[str, Any]) -> str:
    """`0.5 m/s`, or `hover`."""
    return f"{row['speed_m_s']} m/s" if row["speed_m_s"] else "hover"


def flight_line(r: dict[str, Any]) -> str:
    """One row of the main table."""
    e, d, s, n = r["error_mm"], r["setpoint_dev_mm"], r["sigma"], r["nearest"]
    return (
        f"{flight_name(r):>8} {r['masks']:>7} {r['sends']:>5} {r['target_sends']:>4} {r['switches']:>3} "
        f"{fmt(r['first_target_s'], 2):>7} {fmt(e['median'], 1):>7} {fmt(e['p90'], 1):>5} {fmt(e['max'], 1):>6} "
        f"{r['off_5cm']:>4} {r['border_targets']:>4} {fmt(n['ready_delay_s'], 2):>7} "
        f"{'yes' if n['ready'] else 'NO':>5} "
        f"{fmt(d['median'], 0):>6} {fmt(d['max'], 0):>6} {fmt(r['speed_capped'], 2):>6} "
        f"{fmt(s['axis'], 2):>6} {fmt(s['radius'], 2):>5} {fmt(s['radius_expected'], 2):>5} "
        f"{fmt(s.get('sigma_mm'), 1):>5} {fmt(s.get('axis_error_mm'), 1):>5} {fmt(r['release_lag_ms']['max']):>4}"
    )


def band_cell(band: dict[str, Any]) -> str:
    """`p50/p95 (sent/released, late)` of one range band, `—` when no frame was in it."""
    if not band["released"]:
        return "—"
    return f"{fmt(band['p50_ms'])}/{fmt(band['p95_ms'])} ({band['sent']}/{band['released']}, {band['late']})"


def print_report(report: dict[str, Any]) -> None:
    """The tables of the module docstring, and the targets met or not."""
    print(
        f"CPU: {report['cpu']}; {report['threads']} threads; {report['resolution']}; load {report['load']}; "
        f"overrides: {' '.join(report.get('overrides', [])) or 'none'}; "
        f"truth masks: {' '.join(report.get('truth_overrides', [])) or 'the shipped noise'}"
    )
    print(
        f"{'flight':>8} {'masks':>7} {'sends':>5} {'tgt':>4} {'sw':>3} {'first s':>7} {'err med':>7} {'p90':>5} "
        f"{'max mm':>6} {'>5cm':>4} {'bord':>4} {'ready s':>7} {'ok':>5} {'sp med':>6} {'max mm':>6} "
        f"{'capped':>6} {'σ axis':>6} {'σ rad':>5} {'exp':>5} {'σ mm':>5} {'e∥ mm':>5} {'lag':>4}"
    )
    for row in report["flights"]:
        print(flight_line(row))
    print("\ncapture → send, ms: p50/p95 (sent/released, late) by range to the approach's target cut point")
    bands = " ".join(f"{band_label(i) + ' m':>22}" for i in range(len(BAND_EDGES_M) - 1))
    print(f"{'flight':>8} {'masks':>7} {bands}")
    for row in report["flights"]:
        print(f"{flight_name(row):>8} {row['masks']:>7} " + " ".join(f"{band_cell(b):>22}" for b in row["latency_ms"]))
    pooled = ", ".join(f"{m} {fmt(c, 2)}" for m, c in pooled_coverage(report["flights"]).items())
    print(f"\n1-σ coverage along its axis, all sends pooled: {pooled}")
    print("targets: " + "; ".join(f"{k}: {'met' if v else 'NOT met'}" for k, v in report["targets"].items()))


def pool_reports(paths: Sequence[Path]) -> dict[str, Any]:
    """Several runs' reports (`--json`, e.g. other scene seeds) as one: their flights together, the targets over
    all of them; the first run's machine fields, each run's load and every run's overrides kept."""
    reports = [json.loads(path.read_text(encoding="utf-8")) for path in paths]
    pooled = {**reports[0], "flights": [f for r in reports for f in r["flights"]]}
    pooled["load"] = " | ".join(r["load"] for r in reports)
    pooled["overrides"] = list(dict.fromkeys(o for r in reports for o in r.get("overrides", [])))
    pooled["pooled_from"] = [str(path) for path in paths]
    pooled["targets"] = verdicts(pooled["flights"])
    return pooled


def machine_load() -> str:
    """The 1/5/15-minute load averages (the machine is shared; timings depend on them)."""
    import os

    return " ".join(f"{v:.1f}" for v in os.getloadavg())


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line; `--quick` sets the smoke run's resolution, speed and masks."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speeds", default="0.3,0.5,0.8", help="approach speeds, m/s (comma-separated)")
    parser.add_argument("--masks", choices=("truth", "builtin", "both"), default="both")
    parser.add_argument("--resolution", default="1280x720", help="WIDTHxHEIGHT of the rendered flights")
    parser.add_argument("--hover-s", type=float, default=3.0, help="a hover flight at 0.8 m this long (0: none)")
    parser.add_argument("--seed", type=int, default=1, help="scene seed of the rendered flights")
    parser.add_argument("--threads", type=int, default=2, help="OpenCV and torch threads")
    parser.add_argument("--quick", action="store_true", help="smoke run: 640x360, 0.5 m/s, truth masks")
    parser.add_argument("--json", type=Path, help="write the report here")
    parser.add_argument(
        "--pool", type=Path, nargs="+", metavar="REPORT", help="fly nothing: print these --json reports as one run"
    )
    parser.add_argument(
        "--truth-noise",
        type=Path,
        default=TRUTH_NOISE_FILE,
        help="truth-mask flights take [tracking]'s per-view noise from this cut_point_noise.py report (default: "
        "benchmarks/results/cut_point_noise.json; a missing file: the shipped values)",
    )
    parser.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="override the deploy file (repeatable)"
    )
    args = parser.parse_args(argv)
    if args.quick:
        args.resolution, args.speeds, args.masks = "640x360", "0.5", "truth"
    return args


def fly_all(args: argparse.Namespace) -> dict[str, Any]:
    """Render (once) and fly every speed (and the hover) with every mask source; the report."""
    import cv2
    import torch

    cv2.setNumThreads(args.threads)
    torch.set_num_threads(args.threads)
    width = int(args.resolution.lower().split("x")[0])
    speeds: list[float | None] = [float(v) for v in args.speeds.split(",")]
    speeds += [None] if args.hover_s > 0 else []
    masks = ["truth", "builtin"] if args.masks == "both" else [args.masks]
    report: dict[str, Any] = {
        "cpu": cpu_name(),
        "threads": args.threads,
        "resolution": args.resolution,
        "load": machine_load(),
        "config": str(DEPLOY_CONFIG.relative_to(ROOT)),
        "overrides": args.set,
        "truth_overrides": truth_mask_noise(args.truth_noise),
        "flights": [],
    }
    for speed in speeds:
        directory = render_flight(args.resolution, speed, args.hover_s, args.seed)
        for mask in masks:
            print(f"flying {directory.name} with {mask} masks ...", file=sys.stderr)
            report["flights"].append(
                {
                    "speed_m_s": speed,
                    "masks": mask,
                    **run_flight(
                        directory, mask, width, [*(report["truth_overrides"] if mask == "truth" else []), *args.set]
                    ),
                }
            )
    report["targets"] = verdicts(report["flights"])
    return report


def write_json(path: Path, report: dict[str, Any]) -> None:
    """The report as indented JSON at `path` (its folder made when missing)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n")


def main(argv: list[str] | None = None) -> int:
    """Fly, print the tables, write `--json`."""
    args = parse_args(argv)
    report = pool_reports(args.pool) if args.pool else fly_all(args)
    print_report(report)
    if args.json:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
