"""`emcstereo export --onnx OUT`: write the inference graph for ONNX Runtime (the `onnx` backend)."""

from __future__ import annotations

import argparse
import sys

from stereo.checkpoints import load_model
from stereo.commands.train import run_reporting_input_errors
from stereo.commands.weights import add_no_verify_flag
from stereo.export import ExportError, export_onnx
from stereo.model import EMCStereo


def _run(args: argparse.Namespace) -> int:
    return run_reporting_input_errors("export", lambda: _export(args))


def _export(args: argparse.Namespace) -> int:
    if args.weights is None and not args.random_weights:
        raise ExportError(
            "no --weights given: pass a checkpoint (ours, the authors' or PSMNet's), or "
            "--random-weights to export an untrained network for testing"
        )
    if args.weights is not None and args.random_weights:
        raise ExportError("--weights and --random-weights exclude each other")
    if args.random_weights:
        print(
            "warning: exporting a randomly initialised full model (--random-weights): for testing only", file=sys.stderr
        )
    model = EMCStereo() if args.weights is None else load_model(args.weights, verify_sha256=args.verify_sha256)
    path = export_onnx(model, args.onnx, args.height, args.width, args.max_disp)
    print(f"wrote {path} ({args.height}×{args.width}, max_disp {args.max_disp or model.max_disp})")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add `export` to the `emcstereo` command."""
    parser = sub.add_parser("export", help="export the network for ONNX Runtime")
    parser.add_argument("--onnx", required=True, help="output .onnx file")
    parser.add_argument("--weights", help="checkpoint in any supported layout (required unless --random-weights)")
    add_no_verify_flag(parser)
    parser.add_argument(
        "--random-weights", action="store_true", help="export an untrained network (timing and pipeline tests only)"
    )
    parser.add_argument("--height", type=int, default=384, help="padded input height, multiple of 32, ≥ 256")
    parser.add_argument("--width", type=int, default=1248, help="padded input width, multiple of 32, ≥ 256")
    parser.add_argument("--max-disp", type=int, default=None, help="disparity range (default: the model's)")
    parser.set_defaults(func=_run)
