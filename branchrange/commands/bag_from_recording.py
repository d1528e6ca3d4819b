"""`branchrange bag-from-recording`: a recording (branchrange record) → a ROS 2 bag laid out as the ZED wrapper's."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `bag-from-recording` to the `branchrange` command (nothing heavy imported: `--help` stays quick)."""
    p = subparsers.add_parser(
        "bag-from-recording", help="convert a recording into a ROS 2 bag (MCAP or SQLite)", description=__doc__
    )
    p.add_argument("recording", help="a recording directory (branchrange record) or a side-by-side video file")
    p.add_argument("--out", required=True, type=Path, help="new bag directory")
    p.add_argument("--storage", default="mcap", help="rosbag2 storage plugin: mcap (default) or sqlite3")
    p.add_argument(
        "--encoding",
        default="bgra8",
        help="sensor_msgs/Image encoding bgra8 (default, as the ZED wrapper publishes), bgr8, rgb8, mono8; "
        "or jpeg/png as sensor_msgs/CompressedImage",
    )
    p.add_argument("--calibration", type=Path, help="calibration file (overrides the recording's own)")
    for role in ("left", "right", "left_info", "right_info"):
        p.add_argument(
            f"--{role.replace('_', '-')}-topic",
            dest=f"{role}_topic",
            help="topic name (default: the ZED ROS 2 wrapper's since 5.1, e.g. /zed/zed_node/left/color/rect/image)",
        )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Convert; 0 on success, 1 when the recording cannot be read or the bag written, 2 on bad input."""
    from camera import CalibrationError
    from camera.sources import SourceError, open_source
    from camera.sources.rosbag import BagTopics
    from camera.sources.rosbag_writer import BagWriteError, write_bag

    defaults = BagTopics()
    topics = BagTopics(
        *(
            getattr(args, f"{role}_topic") or getattr(defaults, role)
            for role in ("left", "right", "left_info", "right_info")
        )
    )
    try:
        source = open_source(f"replay:{args.recording}", calibration=args.calibration, pace="fast")
    except (SourceError, CalibrationError) as error:
        print(f"branchrange bag-from-recording: {error}", file=sys.stderr)
        return 2
    with source:
        if source.calibration is None:
            print(
                f"branchrange bag-from-recording: {args.recording} has no calibration; pass --calibration FILE",
                file=sys.stderr,
            )
            return 2
        try:
            pairs = write_bag(
                source, source.calibration, args.out, storage=args.storage, encoding=args.encoding, topics=topics
            )
        except BagWriteError as error:
            print(f"branchrange bag-from-recording: {error}", file=sys.stderr)
            return 2
        except (SourceError, ValueError, OSError) as error:
            print(f"branchrange bag-from-recording: {error}", file=sys.stderr)
            return 1
    print(
        f"wrote {pairs} pairs to {args.out} ({args.storage}, {args.encoding}; topics {topics.left}, {topics.right}, "
        f"{topics.left_info}, {topics.right_info})"
    )
    return 0
