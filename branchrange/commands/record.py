"""`branchrange record`: stereo pairs from a camera (or a replay) into a recording directory that replays."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `record` to the `branchrange` command."""
    p = subparsers.add_parser("record", help="record stereo pairs from zed:N, oak or replay:PATH into the replay format",
                              description=__doc__)
    p.add_argument("--source", required=True,
                   help="zed:DEVICE[:MODE] (e.g. zed:0, zed:/dev/video0:HD720), oak[:WxH[@FPS]] or replay:PATH")
    p.add_argument("--out", required=True, type=Path, help="new (or empty) recording directory")
    p.add_argument("--frames", type=int, help="stop after N pairs (default: until the source ends or Ctrl-C)")
    p.add_argument("--calibration", type=Path,
                   help="calibration file stored with the recording (overrides the source's; a ZED SN*.conf is "
                        "read at the mode's resolution)")
    p.add_argument("--image-format", choices=("png", "jpg"), default="png", help="png is lossless (default)")
    p.add_argument("--overwrite", action="store_true", help="allow a non-empty --out")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Record until the source ends, --frames pairs are written or Ctrl-C.

    Returns 0 on success (Ctrl-C included), 1 when recording stopped on an error (what was written
    still replays), 2 on bad input.
    """
    from tqdm import tqdm

    from camera import CalibrationError
    from camera.sources import CorruptFrameError, Recorder, SourceError, open_source, record

    if args.frames is not None and args.frames < 1:
        print(f"branchrange record: --frames is {args.frames}; expected at least 1", file=sys.stderr)
        return 2
    try:
        source = open_source(args.source, calibration=args.calibration, pace="fast")
    except (SourceError, CalibrationError) as error:
        print(f"branchrange record: {error}", file=sys.stderr)
        return 2
    skipped: list[CorruptFrameError] = []
    stopped_by = ""  # why recording ended before the source did or --frames were written
    failed = False
    try:
        with source, Recorder(args.out, calibration=source.calibration, source_spec=args.source,
                              image_format=args.image_format, overwrite=args.overwrite) as recorder, \
                tqdm(total=args.frames, unit="pair", desc="recording", file=sys.stderr) as bar:
            def note_corrupt(error: CorruptFrameError) -> None:
                skipped.append(error)
                bar.write(f"skipped a corrupt frame: {error}", file=sys.stderr)

            try:
                written = record(source, recorder, args.frames, on_frame=lambda _: bar.update(1),
                                 on_corrupt=note_corrupt)
            except KeyboardInterrupt:
                written, stopped_by = recorder.frames, "Ctrl-C"
            except (SourceError, ValueError, OSError) as error:  # camera gone, frame size changed, disk full
                written, stopped_by, failed = recorder.frames, "an error", True
                bar.write(f"branchrange record: {error}", file=sys.stderr)
    except FileExistsError as error:
        print(f"branchrange record: {error} (or pass --overwrite)", file=sys.stderr)
        return 2
    except OSError as error:
        print(f"branchrange record: --out {args.out}: {error}; expected a new or empty directory", file=sys.stderr)
        return 2
    calibration = "with calibration" if source.calibration is not None else "without calibration"
    note = f" (stopped by {stopped_by})" if stopped_by else ""
    print(f"recorded {written} pairs to {args.out} {calibration}{note}"
          + (f"; skipped {len(skipped)} corrupt frames" if skipped else ""))
    return 1 if failed else 0
