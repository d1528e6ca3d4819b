"""`branchrange synth-flight`: render a stereo camera flying toward one synthetic tree into a recording + flight.json.

The recording is the replay format `branchrange record` writes (recording.json, timestamps.csv,
left/, right/, mask/ with uint16 instance ids, calibration.yaml of the rectified ZED Mini rig
scaled to the size), so `branchrange replay`, the daemon's `replay:` source and the benchmarks
read it unchanged; flight.json beside it holds each frame's pose and the true cut points
(`branchrange.offline.flight`). Frame i is captured at i/fps s after a fixed start.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

#: Progress lines when stderr is not a terminal: about this many over a flight.
PROGRESS_LINES = 10


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `synth-flight` to the `branchrange` command."""
    p = subparsers.add_parser(
        "synth-flight",
        help="render a synthetic flight toward a tree into a recording + flight.json",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True, type=Path, help="new (or empty) recording directory")
    p.add_argument(
        "--frames",
        type=int,
        help="number of frames, from --start-m to exactly --end-m (default: as many as --speed takes)",
    )
    p.add_argument("--fps", type=float, default=15.0, help="frame rate, Hz (default 15)")
    p.add_argument("--resolution", default="1280x720", help="WIDTHxHEIGHT in px (default 1280x720, HD720)")
    p.add_argument("--start-m", type=float, default=3.0, help="distance to the target cut point at the first frame, m")
    p.add_argument("--end-m", type=float, default=0.8, help="closest distance to the target cut point, m")
    p.add_argument(
        "--speed",
        type=float,
        help="approach speed, m/s (default 0.4; sets the number of frames: frames are taken while the "
        "distance is ≥ --end-m); not with --frames",
    )
    p.add_argument("--sway-m", type=float, default=0.0, help="lateral sway amplitude, m (default 0)")
    p.add_argument("--sway-hz", type=float, default=0.5, help="lateral sway frequency, Hz (default 0.5)")
    p.add_argument(
        "--jitter-deg",
        type=float,
        default=0.0,
        help="roll/pitch/yaw jitter amplitude, degrees (smooth, 0.3–2 Hz; default 0)",
    )
    p.add_argument(
        "--yaw-rate",
        type=float,
        default=0.0,
        help="yaw sweep about the vertical axis, deg/s: turns at this rate and back before the target "
        "leaves the middle of the image (stereo.synth.flight_path.YAW_BOUND_DEG; default 0)",
    )
    p.add_argument(
        "--exposure",
        type=float,
        default=0.0,
        help="smooth exposure gain changes, relative amplitude (0.2 → ±20%%; default 0)",
    )
    p.add_argument("--motion-blur", action="store_true", help="blur each view along its image motion")
    p.add_argument(
        "--shutter",
        type=float,
        default=0.5,
        help="with --motion-blur: exposure time as a fraction of the frame interval (default 0.5)",
    )
    p.add_argument("--foliage", action="store_true", help="sparse leaves on the twigs (default: a bare tree)")
    p.add_argument("--seed", type=int, default=0, help="scene and path seed (default 0)")
    p.add_argument(
        "--supersample",
        type=int,
        default=1,
        help="rays per pixel side for the images (default 1: an HD720 frame in under a second)",
    )
    p.add_argument("--overwrite", action="store_true", help="allow a non-empty --out")
    p.set_defaults(func=run)


def parse_resolution(text: str) -> tuple[int, int]:
    """`WIDTHxHEIGHT` → (width, height); ValueError naming the text otherwise."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(part.strip().isdigit() for part in parts):
        raise ValueError(f"--resolution is {text!r}; expected WIDTHxHEIGHT in pixels, e.g. 1280x720")
    return int(parts[0]), int(parts[1])


class _Progress:
    """A bar on a terminal; else a plain line every `len/PROGRESS_LINES` frames (logs stay short)."""

    def __init__(self, total: int) -> None:
        from tqdm import tqdm

        self.total, self.done, self.started = total, 0, time.perf_counter()
        self.bar = (
            tqdm(total=total, unit="frame", desc="synth-flight", file=sys.stderr) if sys.stderr.isatty() else None
        )
        self.every = max(1, round(total / PROGRESS_LINES))

    def step(self) -> None:
        self.done += 1
        if self.bar is not None:
            self.bar.update(1)
        elif self.done % self.every == 0 or self.done == self.total:
            per_frame = (time.perf_counter() - self.started) / self.done
            print(
                f"synth-flight: {self.done}/{self.total} frames ({per_frame:.2f} s/frame)", file=sys.stderr, flush=True
            )

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def run(args: argparse.Namespace) -> int:
    """Render and record the flight. Returns 0 on success, 1 when rendering or writing failed, 2 on bad options."""
    import numpy as np

    from branchrange.offline.flight import FlightCutPoint, FlightPose, FlightTruth
    from camera.calibration import from_rectified
    from camera.sources import Recorder, StereoFrame
    from stereo.synth.flight import FlightRenderer
    from stereo.synth.flight_path import FlightOptions

    try:
        width, height = parse_resolution(args.resolution)
        options = FlightOptions(
            frames=args.frames,
            fps=args.fps,
            width=width,
            height=height,
            start_m=args.start_m,
            end_m=args.end_m,
            speed_mps=args.speed,
            sway_m=args.sway_m,
            sway_hz=args.sway_hz,
            jitter_deg=args.jitter_deg,
            yaw_rate_dps=args.yaw_rate,
            exposure=args.exposure,
            motion_blur=args.motion_blur,
            shutter=args.shutter,
            foliage=args.foliage,
            seed=args.seed,
            supersample=args.supersample,
        )
    except ValueError as error:
        print(f"branchrange synth-flight: {error}", file=sys.stderr)
        return 2
    try:
        renderer = FlightRenderer(options)
    except RuntimeError as error:  # the generator found no tree layout for this camera
        print(f"branchrange synth-flight: seed {options.seed} at {args.resolution}: {error}", file=sys.stderr)
        return 2
    cam = renderer.camera
    calibration = from_rectified(
        cam.focal_px,
        cam.cx,
        cam.cy,
        cam.baseline_m,
        (cam.width, cam.height),
        source=f"stereo.synth ZED Mini rig at {cam.width}x{cam.height}",
    )
    cuts = [FlightCutPoint(cut.id, cut.world_m, cut.radius_m) for cut in renderer.cut_points]
    poses: list[FlightPose] = []
    try:
        recorder = Recorder(
            args.out,
            calibration=calibration,
            overwrite=args.overwrite,
            source_spec=f"branchrange synth-flight seed {options.seed}, target {renderer.target_id}",
        )
    except FileExistsError as error:
        print(f"branchrange synth-flight: {error} (or pass --overwrite)", file=sys.stderr)
        return 2
    except OSError as error:
        print(
            f"branchrange synth-flight: --out {args.out}: {error}; expected a new or empty directory", file=sys.stderr
        )
        return 2
    progress = _Progress(len(renderer))
    try:
        with recorder:
            for frame in renderer:
                recorder.write(StereoFrame(frame.left, frame.right, frame.timestamp_ns, frame.index, frame.mask))
                poses.append(
                    FlightPose(
                        frame.index, frame.timestamp_ns, frame.R_world_cam, frame.t_world_cam, frame.visible_cut_ids
                    )
                )
                progress.step()
    except OSError as error:
        print(
            f"branchrange synth-flight: writing {args.out} failed after {len(poses)} frames: {error}", file=sys.stderr
        )
        return 1
    finally:
        progress.close()
        if poses:  # the truth of whatever was recorded, so an interrupted flight still evaluates
            FlightTruth(poses, cuts).write(args.out)
    seconds = time.perf_counter() - progress.started
    seen = np.mean([renderer.target_id in pose.visible_cut_ids for pose in poses])
    print(
        f"wrote {len(poses)} frames ({width}x{height}, {options.fps:g} fps, {options.start_m:g} → "
        f"{options.distance_m(options.time_s(len(poses) - 1)):.2f} m at {options.speed:.3f} m/s) and "
        f"{len(cuts)} cut points to {args.out} in {seconds:.1f} s ({seconds / len(poses):.2f} s/frame); "
        f"target cut point {renderer.target_id} visible in {seen:.0%} of frames"
    )
    return 0
