"""`branchrange replay`: a recording → per-frame results (JSONL) as the daemon gives them, a summary, an
overlay video.

By default every frame is processed, as fast as the computer allows. `--pace recorded` keeps the
recording's schedule instead, as a camera would (frames it has no time for are dropped and counted),
and `--start-at`/`--start-signal` let a simulator or autopilot outside keep in step with it."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from branchrange.commands.config_args import add_config_arguments, config_from_args
from branchrange.commands.exit_codes import BAD_INPUT, DONE, EPILOG, STOPPED_ON_ERROR
from stereo.backends import BACKEND_NAMES


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `replay` to the `branchrange` command."""
    p = subparsers.add_parser(
        "replay",
        help="turn a recording into results, a summary and an overlay video",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "recording",
        help="a recording directory (branchrange record), a folder of pairs (left/ + right/ "
        "[+ mask/]), a side-by-side video file, a ROS 2 bag (directory, .mcap or .db3) "
        "or a rosbag:PATH?left=TOPIC&… spec",
    )
    p.add_argument("--fps", type=float, help="frame rate of a folder of pairs (default 15) or a video's override")
    p.add_argument(
        "--pace",
        choices=("fast", "recorded"),
        default="fast",
        help="fast (default): every frame, as fast as the computer allows; recorded: at the recorded rate, "
        "dropping (and counting) the frames that can no longer be on time, as a camera would",
    )
    p.add_argument(
        "--max-late-ms",
        type=float,
        help="with --pace recorded: how late after its slot a frame may still come, ms (default: half a frame "
        "period; 20 keeps a simulator within 20 ms of the schedule, at the cost of more dropped frames)",
    )
    p.add_argument(
        "--ignore-masks",
        action="store_true",
        help="leave the recording's masks unread: the configured segmenter finds the branches, as for a live camera",
    )
    sync = p.add_argument_group(
        "clock sync", "keep a simulator or autopilot in step with the replay (best with --pace recorded)"
    )
    sync.add_argument(
        "--start-at",
        metavar="TIME",
        help="release the first frame at this wall-clock time: Unix seconds or ISO 8601 with a UTC offset "
        "(2026-11-28T18:10:00Z)",
    )
    sync.add_argument(
        "--start-signal",
        action="append",
        default=[],
        metavar="file:PATH|udp:HOST:PORT",
        help="announce the first frame's release (branchrange/replay-start/v1 JSON: wall_ns, monotonic_ns, "
        "first_timestamp_ns, first_index) in a file and/or one UDP datagram (repeatable); it is also logged",
    )
    p.add_argument(
        "--out", required=True, help="results: a run header line, then one branchrange/v1 JSON line per frame"
    )
    p.add_argument(
        "--overlay-video",
        help="write an overlay video here (.mp4 with mp4v; .avi with MJPG when this OpenCV cannot write mp4v)",
    )
    p.add_argument(
        "--summary", action="store_true", help="print a summary and write it as JSON next to --out (NAME.summary.json)"
    )
    add_config_arguments(
        p,
        required=False,
        sections="as the daemon reads it: [camera] calibration, [stereo], [roi], "
        "[cutpoints], [branch_tracking], [masks], [segmenter], [log]",
    )
    p.add_argument("--backend", choices=BACKEND_NAMES, help="stereo backend (overrides stereo.backend)")
    p.add_argument("--weights", help="EMCStereo weights (overrides stereo.weights)")
    p.add_argument("--max-disp", type=int, help="largest disparity searched, px (overrides stereo.max_disp)")
    p.add_argument(
        "--foxglove",
        action="append",
        default=[],
        metavar="FILE.mcap|ws://HOST:PORT",
        help="also send every frame to Foxglove: write an MCAP file and/or serve a live WebSocket "
        "(repeat for both); open with deploy/foxglove_layout.json",
    )
    p.add_argument(
        "--mount-rpy-deg",
        nargs=3,
        type=float,
        metavar=("ROLL", "PITCH", "YAW"),
        help="the camera's mount on the vehicle, as the daemon's camera.mount_rpy_deg (overrides it): "
        "places the camera on body_frd in the Foxglove transform tree",
    )
    p.add_argument(
        "--mount-xyz-m",
        nargs=3,
        type=float,
        metavar=("X", "Y", "Z"),
        help="the camera's optical centre in body FRD metres, as camera.mount_xyz_m (overrides it)",
    )
    p.set_defaults(func=run)


def summary_path(out: str | Path) -> Path:
    """Where `--summary` writes its JSON: beside the results file, `results.summary.json` for `results.jsonl`."""
    out = Path(out)
    return out.with_name(out.stem + ".summary.json")


def run(args: argparse.Namespace) -> int:
    """Load the config with the command line's overrides, replay, print and write the summary."""
    from branchrange.core.settings_check import ConfigError
    from branchrange.offline.overlay_video import VideoWriteError
    from branchrange.offline.replay import replay_recording, source_spec
    from branchrange.onboard.foxglove_sink import FoxgloveSink, FoxgloveTargetError, parse_targets
    from branchrange.onboard.mavlink import CameraMount
    from camera.sources import SourceConfigError, SourceError
    from camera.sources.clock_sync import ClockSync

    try:
        cfg = config_from_args(
            args,
            {
                "stereo.backend": args.backend,
                "stereo.weights": args.weights,
                "stereo.max_disp": args.max_disp,
                "camera.source": source_spec(args.recording),
                "camera.mount_rpy_deg": args.mount_rpy_deg,
                "camera.mount_xyz_m": args.mount_xyz_m,
            },
        )
        targets = parse_targets(args.foxglove) if args.foxglove else None
        clock_sync = ClockSync.parse(args.start_at, args.start_signal) if args.start_at or args.start_signal else None
    except (ConfigError, FoxgloveTargetError, SourceConfigError) as exc:
        print(f"branchrange replay: {exc}", file=sys.stderr)
        return BAD_INPUT
    if args.fps is not None and not args.fps > 0:
        print(f"branchrange replay: --fps is {args.fps}; expected a positive frame rate", file=sys.stderr)
        return BAD_INPUT
    if args.max_late_ms is not None and (args.pace != "recorded" or not args.max_late_ms > 0):
        print(
            f"branchrange replay: --max-late-ms is {args.max_late_ms}; expected milliseconds > 0 with --pace recorded",
            file=sys.stderr,
        )
        return BAD_INPUT
    logging.basicConfig(level=cfg.log.level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    sink = None
    try:
        mount = CameraMount.from_rpy(cfg.camera.mount_rpy_deg, cfg.camera.mount_xyz_m)
        sink = FoxgloveSink(targets, mount=mount) if targets else None
        summary = replay_recording(
            args.recording,
            cfg,
            args.out,
            video=args.overlay_video,
            observers=[sink] if sink else [],
            fps=args.fps,
            pace=args.pace,
            ignore_masks=args.ignore_masks,
            clock_sync=clock_sync,
            max_late_ms=args.max_late_ms,
        )
    except (SourceError, ValueError) as exc:  # recording missing / truncated / unreadable, or settings it cannot use
        print(f"branchrange replay: {exc}", file=sys.stderr)
        return BAD_INPUT
    except VideoWriteError as exc:
        print(f"branchrange replay: {exc}", file=sys.stderr)
        return STOPPED_ON_ERROR
    finally:
        if sink is not None:
            sink.close()
    if summary.frames == 0 and summary.corrupt and not summary.rejected:
        print(
            f"branchrange replay: none of the {summary.corrupt} frames of {args.recording} could be read; "
            "expected a readable recording (see the warnings above)",
            file=sys.stderr,
        )
        return BAD_INPUT
    late = f"; {summary.dropped_late} frames dropped as too late" if args.pace == "recorded" else ""
    print(f"results: {args.out} (a run header and {summary.frames} result lines{late})")
    if sink is not None:
        print(f"foxglove: {sink.describe()} (open it in Foxglove with deploy/foxglove_layout.json)")
    if args.summary:
        path = summary_path(args.out)
        path.write_text(json.dumps(summary.to_dict(), indent=2) + "\n", encoding="utf-8")
        print(summary.text())
        print(f"summary: {path}")
    elif summary.video:
        print(f"overlay video: {summary.video} ({summary.video_codec})")
    return DONE if summary.frames else STOPPED_ON_ERROR
