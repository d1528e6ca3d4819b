"""`branchrange export-frames`: the frames of a recording worth labelling, as a COCO data set pre-annotated with
today's masks, to correct in CVAT or Label Studio.

Frames are picked uncertain (low cut-point confidence, the learned and structure segmenters disagreeing)
and diverse (colour, nearness), at least --min-spacing-s apart; see branchrange.offline.frame_selection.
"""

from __future__ import annotations

import argparse
import sys

from branchrange.commands.config_args import add_config_arguments, config_from_args
from branchrange.commands.exit_codes import BAD_INPUT, DONE, EPILOG, STOPPED_ON_ERROR


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `export-frames` to the `branchrange` command (nothing heavy imported: `--help` stays quick)."""
    p = subparsers.add_parser(
        "export-frames",
        help="pick frames worth labelling and write them as a COCO data set (CVAT, Label Studio)",
        description=__doc__,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "source",
        help="a recording directory (branchrange record), a folder of pairs, a side-by-side video, a ROS 2 bag "
        "(directory, .mcap or .db3), a replay:/rosbag: spec, or a replay's results .jsonl (its recording)",
    )
    p.add_argument("--out", required=True, help="data set directory: images/, annotations.json (+ _polygons)")
    p.add_argument("--count", type=int, default=50, help="frames to pick (default 50)")
    p.add_argument(
        "--min-spacing-s", type=float, default=2.0, help="least time between two picked frames, s (default 2)"
    )
    p.add_argument("--every", type=int, default=1, help="score every N-th frame only (long recordings; default 1)")
    p.add_argument(
        "--segmenter",
        metavar="NAME",
        help="segmenter of the pre-annotations when the recording has no masks: 'learned' (default), "
        "'learned:BUNDLE', 'structure', 'geometric' or 'onnx:FILE' (overrides segmenter.model)",
    )
    add_config_arguments(
        p, required=False, sections="[camera] calibration, [stereo], [masks], [segmenter] as the daemon reads them"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Export; 0 done, 1 when the data set could not be written, 2 on bad input (nothing written)."""
    from branchrange.offline.coco_export import CocoExportError
    from branchrange.offline.frame_export import export_frames
    from camera.sources import SourceError
    from stereo.cli import package_version

    try:
        cfg = config_from_args(args, {"segmenter.model": args.segmenter})
        summary = export_frames(
            args.source,
            cfg,
            args.out,
            count=args.count,
            min_spacing_s=args.min_spacing_s,
            every=args.every,
            version=package_version(),
        )
    except (SourceError, ValueError) as exc:  # the source cannot be read, or settings it cannot use
        print(f"branchrange export-frames: {exc}", file=sys.stderr)
        return BAD_INPUT
    except (CocoExportError, OSError) as exc:  # pycocotools missing, or the data set not writable
        print(f"branchrange export-frames: {exc}", file=sys.stderr)
        return STOPPED_ON_ERROR
    print(
        f"scored {summary.scored} frames of {summary.source} ({summary.corrupt} unreadable, "
        f"{summary.rejected} rejected by the pipeline); "
        f"picked {len(summary.picked)}: {', '.join(str(s.index) for s in summary.picked)}"
    )
    print(f"wrote {summary.annotations} (import into CVAT as COCO 1.0; Label Studio: annotations_polygons.json)")
    return DONE
