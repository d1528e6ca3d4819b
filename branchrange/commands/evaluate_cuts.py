"""`branchrange evaluate-cuts DIR`: cut-point accuracy over a synthetic set from `emcstereo synth`.

Prints one table row per (stereo, masks) combination: recall within 5 cm (with its 95 % interval from a
bootstrap over the frames), median and 90th-percentile 3D cut-point error, median distance error in % of
the range, false cut points per frame, and how often the frame's target lies within 5 cm of a true cut
point. Stereo
'gt' uses the set's exact disparity (the geometry's own error); 'emcstereo' needs --weights.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `evaluate-cuts` to the `branchrange` command."""
    p = subparsers.add_parser("evaluate-cuts", help="cut-point accuracy over a synthetic set", description=__doc__)
    p.add_argument("dir", type=Path, help="a set written by `emcstereo synth --out DIR`")
    p.add_argument(
        "--stereo",
        nargs="+",
        choices=("gt", "sgbm", "emcstereo"),
        help="stereo modes (default: gt sgbm, plus emcstereo with --weights)",
    )
    p.add_argument(
        "--masks",
        nargs="+",
        choices=("gt", "segmenter"),
        default=["gt", "segmenter"],
        help="mask modes (default: gt segmenter)",
    )
    p.add_argument("--weights", type=Path, help="EMCStereo checkpoint for the emcstereo mode")
    p.add_argument("--max-disp", type=int, default=192, help="disparity search range in px (default 192)")
    p.add_argument("--limit", type=int, help="evaluate the first N scenes only")
    p.add_argument("--split", choices=("train", "val", "test"), help="evaluate one split's scenes only")
    p.add_argument(
        "--min-confidence",
        type=float,
        default=0.0,
        help="ignore estimated cut points below this confidence (default 0: count all)",
    )
    p.add_argument(
        "--target-policy",
        help="how each frame's target is chosen, scored in the target@5cm column "
        "(nearest_confident, nearest, most_confident, thickest; default: the pipeline's, nearest_confident)",
    )
    p.add_argument("--json", type=Path, help="also write the scores as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Evaluate and print the table."""
    from branchrange.core.cutpoints import DEFAULT_TARGET_POLICY
    from branchrange.core.pipeline import untracked_whole_frame
    from branchrange.offline.evaluate_cuts import evaluate_cuts, format_table, scores_as_dict

    stereo = args.stereo or (["gt", "sgbm"] + (["emcstereo"] if args.weights else []))
    try:
        scores = evaluate_cuts(
            args.dir,
            stereo,
            args.masks,
            weights=str(args.weights) if args.weights else None,
            max_disp=args.max_disp,
            limit=args.limit,
            split=args.split,
            min_confidence=args.min_confidence,
            config=untracked_whole_frame(args.max_disp, args.target_policy or DEFAULT_TARGET_POLICY),
        )
    except (ValueError, OSError) as exc:
        print(f"branchrange evaluate-cuts: error: {exc}", file=sys.stderr)
        return 2
    print(format_table(scores))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(scores_as_dict(scores), indent=1) + "\n", encoding="utf-8")
    return 0
