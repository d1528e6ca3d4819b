"""Latency compensation: the body-frame target the autopilot receives, with and without vehicle-pose fusion.

A loopback autopilot (`tests/autopilot_sim.py`: real MAVLink 2 over UDP on 127.0.0.1, HEARTBEAT,
SET_MESSAGE_INTERVAL answered, ATTITUDE + LOCAL_POSITION_NED at 50 Hz, its own boot clock) flies
a copter toward a branch at each `--speeds` value (with 5 cm sideways sway, ±6° yaw swing, ±3°
roll/pitch), while this script plays the daemon through a real `MavlinkRelay`: frames captured
at 15 Hz, each published `latency` seconds after capture (`--latencies`) with its capture time and
the true cut point seen from the true camera pose plus stereo-like noise (depth σ 1 cm·r², lateral
σ 4 mm·r, the tracker's defaults). Every DEBUG_VECT "CUT" the autopilot receives from the 6th frame
on is compared with the true cut point in the body frame *at the moment it arrived*:
- `compensated`: what the relay sent (fused in local NED, re-expressed in the newest pose);
- `uncompensated` (the baseline, measured in the same run from the same frames): the newest
  result's cut point through the camera mount alone, what the relay sent before vehicle state
  (and still sends without it). Without vehicle state a result older than
  `mavlink.max_result_age_s` (0.5 s) is not sent at all; the column shows the error it would have.
Numbers are millimetres (median, p95 over sends; `--repeats` flights per cell pooled), and the
ratio uncompensated / compensated of the medians.

`--flight DIR` runs the whole chain instead: the daemon (`branchrange.onboard.daemon.Daemon`, sgbm, the
recording's truth masks, `--stereo-mode` roi) replays a `branchrange synth-flight` recording at its frame rate while the
simulator flies the poses of its `flight.json` (hovering at the first pose until the first frame
is released); reported: the fused target track against the true cut point (local NED), the
single-frame target cut points against the truth (camera frame at capture), and the body-frame
target at arrival, compensated (the fused target against the nearest true cut point: it may be
another branch than the newest frame's target) and not (against its own branch's).

    .venv/bin/python benchmarks/pose_compensation.py --json out/pose_compensation.json
    .venv/bin/python -m branchrange.cli synth-flight --out /tmp/flight --frames 20 --fps 8 \\
        --resolution 640x360 --start-m 2.0 --end-m 1.0 --seed 1
    .venv/bin/python benchmarks/pose_compensation.py --flight /tmp/flight --json out/pose_flight.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "benchmarks")]

from autopilot_sim import AutopilotSim, approach_flight, body_target_errors, fly_daemon, fly_frames  # noqa: E402
from machine import cpu_name  # noqa: E402

from branchrange.config.sections import MavlinkConfig, TrackingConfig  # noqa: E402
from branchrange.onboard.mavlink import CameraMount, MavlinkRelay  # noqa: E402

FPS = 15.0
MOUNT = CameraMount.from_rpy((0.0, -10.0, 0.0), (0.12, 0.0, 0.04))
START = np.array([0.0, 0.0, -2.0])
HEADING_DEG = 20.0
SKIP_FRAMES = 5


def target_ned(distance_m: float) -> np.ndarray:
    """The branch `distance_m` ahead of the start along the heading, 10 cm below the flight level."""
    h = math.radians(HEADING_DEG)
    return START + distance_m * np.array([math.cos(h), math.sin(h), 0.0]) + np.array([0.0, 0.0, 0.1])


def one_flight(speed: float, latency: float, frames: int, seed: int) -> tuple[list[float], list[float]]:
    """Errors (m) of compensated and uncompensated sends over one simulated approach."""
    tracking = TrackingConfig()
    # far enough that the branch stays ahead during the whole flight (closest ~0.8 m)
    cut = target_ned(0.8 + speed * (latency + frames / FPS))
    with AutopilotSim(
        approach_flight(speed, start_ned_m=tuple(START), heading_deg=HEADING_DEG), heartbeat_period_s=0.2
    ) as sim:
        cfg = MavlinkConfig(url=f"udpout:127.0.0.1:{sim.port}", send_rate_hz=10.0, state_rate_hz=50.0)
        with MavlinkRelay(cfg, MOUNT, tracking=tracking) as relay:
            deadline = time.monotonic() + 5.0
            while not relay.link_state()["vehicle_state"]["available"]:
                if time.monotonic() > deadline:
                    raise SystemExit(f"no vehicle state from the simulator: {relay.link_state()}")
                time.sleep(0.02)
            published = fly_frames(
                sim, relay, MOUNT, [cut], frames, FPS, latency, np.random.default_rng(seed), tracking
            )
            time.sleep(0.2)
        return body_target_errors(sim, published, MOUNT, cut, SKIP_FRAMES)


def daemon_flight(directory: Path, max_disp: int, stereo_mode: str) -> dict[str, Any]:
    """The daemon replays `directory` while the simulator flies its flight.json; errors in metres."""
    from branchrange.config.loader import Config
    from branchrange.config.sections import CameraConfig, LogConfig
    from branchrange.core.pipeline import StereoConfig

    cfg = Config(
        camera=CameraConfig(
            source=f"replay:{directory}", mount_rpy_deg=(0.0, -10.0, 0.0), mount_xyz_m=(0.12, 0.0, 0.04)
        ),
        stereo=StereoConfig(max_disp=max_disp, mode=stereo_mode),
        log=LogConfig(status_interval_s=3600.0),
        mavlink=MavlinkConfig(send_rate_hz=10.0, state_rate_hz=50.0),
    )
    flight = fly_daemon(directory, cfg, MOUNT, start_ned_m=tuple(START), heading_deg=HEADING_DEG)
    truth, sim, published, targets = flight.truth, flight.sim, flight.published, flight.final_targets
    cuts_ned = flight.cuts_ned()
    single, compensated, uncompensated = [], [], []
    for _, result in published:
        branch = result.target
        if branch is None or branch.mask_id not in cuts_ned:
            continue
        position = next(i for i, p in enumerate(truth.poses) if p.index == result.frame.index)
        single.append(
            float(np.linalg.norm(np.asarray(branch.cut_point_m) - truth.cut_points_in_camera(position)[branch.mask_id]))
        )
    for r in sim.of_type("DEBUG_VECT"):
        newest = [res for at, res in published if at <= r.at]
        target = newest[-1].target if newest else None
        if len(newest) <= SKIP_FRAMES or target is None or target.mask_id not in cuts_ned or math.isnan(r.msg.x):
            continue
        pose = sim.pose_at(r.at)
        # the fused target is chosen on evidence with hysteresis, so it may be another branch than the newest
        # frame's target: each is scored against the true cut point of its own branch
        sent = np.array([r.msg.x, r.msg.y, r.msg.z])
        compensated.append(min(float(np.linalg.norm(sent - pose.ned_to_body(c))) for c in cuts_ned.values()))
        body_truth = pose.ned_to_body(cuts_ned[target.mask_id])
        uncompensated.append(float(np.linalg.norm(MOUNT.to_body(target.cut_point_m) - body_truth)))
    track = next((t for t in targets.tracks if t.id == targets.target_track_id), None)
    fused = None
    if track is not None:
        nearest = min(cuts_ned, key=lambda i: float(np.linalg.norm(np.asarray(track.ned_m) - cuts_ned[i])))
        fused = {
            "cut_id": nearest,
            "error_mm": round(1000 * float(np.linalg.norm(np.asarray(track.ned_m) - cuts_ned[nearest])), 2),
            "observations": track.observations,
            "sigma_mm": round(1000 * track.sigma_m, 2),
        }
    latencies = [
        res.latency.capture_to_publish_ms for _, res in published if res.latency and res.latency.capture_to_publish_ms
    ]
    return {
        "flight": str(directory),
        "frames_published": len(published),
        "fused_target": fused,
        "latency_ms_median": round(float(np.median(latencies)), 1) if latencies else None,
        "single_frame_target": summary(single),
        "compensated": summary(compensated),
        "uncompensated": summary(uncompensated),
        "sends": len(compensated),
    }


def summary(errors: list[float]) -> dict[str, float | None]:
    """Median and p95 in millimetres (None when nothing was sent)."""
    if not errors:
        return {"median_mm": None, "p95_mm": None}
    return {
        "median_mm": round(1000 * float(np.median(errors)), 2),
        "p95_mm": round(1000 * float(np.percentile(errors, 95)), 2),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speeds", default="0.3,0.5", help="approach speeds, m/s (comma-separated)")
    parser.add_argument("--latencies", default="0.2,0.5,1.0", help="capture → publish latencies, s (comma-separated)")
    parser.add_argument("--frames", type=int, default=20, help="frames per flight (15 fps)")
    parser.add_argument("--repeats", type=int, default=3, help="flights per cell, pooled")
    parser.add_argument("--json", type=Path, help="write the report here")
    parser.add_argument(
        "--flight", type=Path, help="a `branchrange synth-flight` recording: run the daemon on it instead"
    )
    parser.add_argument("--max-disp", type=int, default=64, help="sgbm disparities with --flight")
    parser.add_argument(
        "--stereo-mode", default="roi", help="stereo.mode with --flight: 'roi' (onboard default) or 'full'"
    )
    args = parser.parse_args(argv)
    if args.flight:
        report = {"cpu": cpu_name(), **daemon_flight(args.flight, args.max_disp, args.stereo_mode)}
        print(json.dumps(report, indent=2))
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(report, indent=2))
        return 0
    speeds = [float(v) for v in args.speeds.split(",")]
    latencies = [float(v) for v in args.latencies.split(",")]
    cells = []
    for speed in speeds:
        for latency in latencies:
            comp, uncomp = [], []
            for repeat in range(args.repeats):
                c, u = one_flight(speed, latency, args.frames, seed=repeat)
                comp += c
                uncomp += u
            cell = {
                "speed_m_s": speed,
                "latency_s": latency,
                "sends": len(comp),
                "compensated": summary(comp),
                "uncompensated": summary(uncomp),
            }
            cell["ratio"] = (
                round(cell["uncompensated"]["median_mm"] / max(cell["compensated"]["median_mm"], 1e-6), 1)
                if comp
                else None
            )
            cells.append(cell)
            print(f"  {speed} m/s, {latency} s: done", file=sys.stderr)
    report: dict[str, Any] = {
        "cpu": cpu_name(),
        "fps": FPS,
        "state_rate_hz": 50.0,
        "repeats": args.repeats,
        "frames": args.frames,
        "cells": cells,
    }
    print(
        f"CPU: {report['cpu']}; {args.repeats} flights × {args.frames} frames per row; error of the body-frame target "
        "at arrival, mm"
    )
    print(
        f"{'speed m/s':>9} {'latency s':>9} {'sends':>6} {'comp. median':>12} {'comp. p95':>9} "
        f"{'uncomp. median':>14} {'uncomp. p95':>11} {'ratio':>6}"
    )
    for c in cells:
        print(
            f"{c['speed_m_s']:>9} {c['latency_s']:>9} {c['sends']:>6} {c['compensated']['median_mm']:>12} "
            f"{c['compensated']['p95_mm']:>9} {c['uncompensated']['median_mm']:>14} {c['uncompensated']['p95_mm']:>11} "
            f"{c['ratio']:>6}"
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
