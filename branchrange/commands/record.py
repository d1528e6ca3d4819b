"""`branchrange record`: stereo pairs from a camera (or a replay) into a recording directory that replays."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from branchrange.commands.exit_codes import BAD_INPUT, DONE, EPILOG, STOPPED_ON_ERROR


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `record` to the `branchrange` command."""
    p = subparsers.add_parser(
        "record",
        help="record stereo pairs from zed:N, oak or replay:PATH into the replay format",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--source",
        required=True,
        help="zed:DEVICE[:MODE] (e.g. zed:0, zed:/dev/video0:HD720), oak[:WxH[@FPS]] or replay:PATH "
        "(a recording, a folder of pairs PATH/left/*.png + PATH/right/*.png [+ PATH/mask/], or a "
        "side-by-side video)",
    )
    p.add_argument(
        "--fps",
        type=float,
        help="frame rate of a folder of pairs (default 15; it has no timestamps) or "
        "a video's, overriding what it reports",
    )
    p.add_argument("--out", required=True, type=Path, help="new (or empty) recording directory")
    p.add_argument("--frames", type=int, help="stop after N pairs (default: until the source ends or Ctrl-C)")
    p.add_argument(
        "--calibration",
        type=Path,
        help="calibration file stored with the recording (overrides the source's; a ZED SN*.conf is "
        "read at the mode's resolution)",
    )
    p.add_argument("--image-format", choices=("png", "jpg"), default="png", help="png is lossless (default)")
    p.add_argument("--overwrite", action="store_true", help="allow a non-empty --out")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Record until the source ends, --frames pairs are written or Ctrl-C.

    Exit codes as in `exit_codes` (Ctrl-C counts as done): 0 done, 1 stopped on an error (what
    was written still replays), 2 bad input.
    """
    from camera import CalibrationError
    from camera.sources import CorruptFrameError, Recorder, SourceError, open_source, record
    from stereo.progress import progress_bar

    if args.frames is not None and args.frames < 1:
        print(f"branchrange record: --frames is {args.frames}; expected at least 1", file=sys.stderr)
        return BAD_INPUT
    if args.fps is not None and not args.fps > 0:
        print(f"branchrange record: --fps is {args.fps}; expected a positive frame rate", file=sys.stderr)
        return BAD_INPUT
    try:
        source = open_source(args.source, calibration=args.calibration, pace="fast", fps=args.fps)
    except (SourceError, CalibrationError) as error:
        print(f"branchrange record: {error}", file=sys.stderr)
        return BAD_INPUT
    skipped: list[CorruptFrameError] = []
    stopped_by = ""  # why recording ended before the source did or --frames were written
    failed = False
    try:
        with (
            source,
            Recorder(
                args.out,
                calibration=source.calibration,
                source_spec=args.source,
                image_format=args.image_format,
                overwrite=args.overwrite,
            ) as recorder,
            progress_bar(total=args.frames, unit="pair", desc="recording") as bar,
        ):

            def note_corrupt(error: CorruptFrameError) -> None:
                skipped.append(error)
                bar.write(f"skipped a corrupt frame: {error}", file=sys.stderr)

            try:
                written = record(
                    source, recorder, args.frames, on_frame=lambda _: bar.update(1), on_corrupt=note_corrupt
                )
            except KeyboardInterrupt:
                written, stopped_by = recorder.frames, "Ctrl-C"
            except (SourceError, ValueError, OSError) as error:  # camera gone, frame size changed, disk full
                written, stopped_by, failed = recorder.frames, "an error", True
                bar.write(f"branchrange record: {error}", file=sys.stderr)
    except FileExistsError as error:
        print(f"branchrange record: {error} (or pass --overwrite)", file=sys.stderr)
        return BAD_INPUT
    except OSError as error:
        print(f"branchrange record: --out {args.out}: {error}; expected a new or empty directory", file=sys.stderr)
        return BAD_INPUT
    if written == 0 and skipped and not failed:
        print(
            f"branchrange record: none of the {len(skipped)} frames of {args.source} could be read "
            f"(first: {skipped[0]}); expected a readable recording",
            file=sys.stderr,
        )
        return BAD_INPUT
    calibration = "with calibration" if source.calibration is not None else "without calibration"
    note = f" (stopped by {stopped_by})" if stopped_by else ""
    print(
        f"recorded {written} pairs to {args.out} {calibration}{note}"
        + (f"; skipped {len(skipped)} corrupt frames" if skipped else "")
    )
    return STOPPED_ON_ERROR if failed else DONE
