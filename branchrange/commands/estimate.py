"""`branchrange estimate`: cut points of one stereo pair, as `branchrange/v1` JSON and an overlay image.

The camera is either a calibration file (ZED conf, OpenCV YAML/XML, depthai JSON, KITTI; raw
pairs are rectified unless --rectified) or the focal length and baseline of an already rectified
pair. Without --mask a segmenter proposes the branches: the built-in 'learned' one (BranchNet; or the
weight-free 'structure' and 'geometric'), or your own ONNX model with --segmenter onnx:FILE.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from branchrange.core.frame_result import FrameResult

#: Exit status for input the command cannot use (bad file, size, calibration …).
EXIT_BAD_INPUT = 2


def branch_table(result: FrameResult) -> str:
    """A plain-text table of a result's cut points (one row per branch, the target starred)."""
    rows = [f"{'id':>4} {'x':>7} {'y':>7} {'z':>7} {'dist m':>7} {'diam mm':>7} {'conf':>5}  target"]
    for b in result.branches:
        x, y, z = b.cut_point_m
        star = "*" if result.is_target(b) else ""
        rows.append(
            f"{b.id:>4} {x:>7.3f} {y:>7.3f} {z:>7.3f} {b.distance_m:>7.3f} "
            f"{b.diameter_m * 1000:>7.1f} {b.confidence:>5.2f}  {star}"
        )
    if not result.branches:
        rows.append(f"  (no cut points: {result.reason or 'none found'})")
    return "\n".join(rows)


def add_stereo_arguments(parser: argparse.ArgumentParser, default_backend: str | None) -> None:
    """--backend/--weights/--max-disp, shared by the commands that run a stereo backend."""
    from stereo.backends import BACKEND_NAMES, MAX_DISP_EXPECTED

    parser.add_argument(
        "--backend",
        choices=BACKEND_NAMES,
        default=default_backend,
        help="stereo backend (default: emcstereo with --weights, else sgbm)",
    )
    parser.add_argument(
        "--weights", type=Path, help="EMCStereo checkpoint (any supported layout), or the .onnx file of --backend onnx"
    )
    parser.add_argument(
        "--max-disp",
        type=int,
        default=192,
        help=f"disparity search range (stereo.max_disp): {MAX_DISP_EXPECTED} (default 192)",
    )


def chosen_backend(args: argparse.Namespace) -> str:
    """The backend the user asked for, or emcstereo when weights were given and sgbm otherwise."""
    from stereo.backends import WEIGHTED_BACKENDS

    if args.backend is not None:
        if args.backend in WEIGHTED_BACKENDS and args.weights is None:
            raise ValueError(f"--backend {args.backend} needs --weights: an untrained network gives meaningless depth")
        return args.backend
    return "emcstereo" if args.weights is not None else "sgbm"


def whole_frame_stereo(args: argparse.Namespace) -> Any:
    """The `[stereo]` settings of --backend/--weights/--max-disp for one pair: whole-frame matching
    (ConfigError naming `stereo.max_disp` … for a value out of range)."""
    from branchrange.core.pipeline import StereoConfig

    return StereoConfig(
        backend=chosen_backend(args), weights=str(args.weights or ""), max_disp=args.max_disp, mode="full"
    )


def add_segmenter_arguments(parser: argparse.ArgumentParser, *, optional_value: bool) -> None:
    """--segmenter NAME and an onnx model's class ids, thresholds and input size, shared by `estimate`
    and `demo` (the other commands set them as `[segmenter]` keys, `--set segmenter.nms_iou=0.6`).

    `optional_value`: a bare `--segmenter` means the default segmenter and leaving it out means no
    segmenter (demo: the truth mask); otherwise it defaults to the default segmenter.
    """
    from branchrange.core.segmentation.choose import DEFAULT_SEGMENTER
    from branchrange.core.segmentation.choose import SEGMENTER_NAMES as names
    from branchrange.core.segmentation.onnx_model import OnnxSegmenterConfig as onnx

    if optional_value:
        parser.add_argument(
            "--segmenter",
            nargs="?",
            const=DEFAULT_SEGMENTER,
            metavar="NAME",
            help=f"find branches with a segmenter, not the truth mask: {names}; bare = {DEFAULT_SEGMENTER}",
        )
    else:
        parser.add_argument(
            "--segmenter",
            default=DEFAULT_SEGMENTER,
            metavar="NAME",
            help=f"segmenter used without --mask: {names} (default {DEFAULT_SEGMENTER})",
        )
    parser.add_argument(
        "--branch-classes",
        type=int,
        nargs="+",
        default=[0],
        metavar="ID",
        help="class ids an onnx model uses for branches (default 0)",
    )
    parser.add_argument(
        "--trunk-classes",
        type=int,
        nargs="*",
        default=[],
        metavar="ID",
        help="class ids an onnx model uses for the trunk (default none)",
    )
    for key, kind, metavar, what in (
        ("score_threshold", float, "S", "an onnx model's detections scoring lower are dropped (Ultralytics' conf)"),
        (
            "nms_iou",
            float,
            "IOU",
            "an onnx model's NMS drops the weaker of two same-class boxes overlapping more (Ultralytics' iou)",
        ),
        (
            "input_size",
            int,
            "PX",
            "input side a dynamic-shape onnx model runs at (0: the imgsz in its metadata, else 640)",
        ),
    ):
        default = getattr(onnx, key)
        parser.add_argument(
            f"--{key.replace('_', '-')}", type=kind, default=default, metavar=metavar, help=f"{what}; default {default}"
        )


def segmenter_settings(args: argparse.Namespace) -> Any:
    """The `[segmenter]` settings of the segmenter options (ValueError on bad ones)."""
    from branchrange.core.segmentation.choose import DEFAULT_SEGMENTER, SegmenterConfig

    return SegmenterConfig(
        model=args.segmenter or DEFAULT_SEGMENTER,
        branch_classes=tuple(args.branch_classes),
        trunk_classes=tuple(args.trunk_classes),
        score_threshold=args.score_threshold,
        nms_iou=args.nms_iou,
        input_size=args.input_size,
    )


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `estimate` to the `branchrange` command."""
    p = subparsers.add_parser("estimate", help="cut points of one stereo pair", description=__doc__)
    p.add_argument("--left", type=Path, required=True, help="left image (PNG/JPEG)")
    p.add_argument("--right", type=Path, required=True, help="right image, same size")
    camera = p.add_mutually_exclusive_group(required=True)
    camera.add_argument("--calib", type=Path, help="calibration file (format detected from its content)")
    camera.add_argument("--focal-px", type=float, help="rectified focal length in px (with --baseline-m)")
    p.add_argument("--baseline-m", type=float, help="baseline in metres (with --focal-px)")
    p.add_argument(
        "--principal-point",
        type=float,
        nargs=2,
        metavar=("CX", "CY"),
        help="rectified principal point in px (with --focal-px; default the image centre)",
    )
    p.add_argument(
        "--doffs",
        type=float,
        metavar="PX",
        help="disparity offset of the rectified pair (Middlebury 2014 doffs): Z = f·B/(d + doffs); "
        "with --focal-px (a Middlebury calib.txt given to --calib carries its own)",
    )
    p.add_argument("--resolution", help="resolution section of a ZED calibration file (2K, FHD, HD, VGA)")
    p.add_argument("--rectified", action="store_true", help="the images are already rectified: do not rectify")
    p.add_argument("--mask", type=Path, help="instance-id PNG (8/16-bit) or binary mask; default: segmenter")
    p.add_argument("--trunk-id", type=int, default=65535, help="trunk id in the instance mask (default 65535)")
    add_segmenter_arguments(p, optional_value=False)
    add_stereo_arguments(p, None)
    p.add_argument("--json", type=Path, help="write the result JSON here (default: print it)")
    p.add_argument("--overlay", type=Path, help="write the overlay image here (PNG)")
    p.set_defaults(func=run)


def _settings(args: argparse.Namespace) -> Any:
    """The `PipelineConfig` of the options: one pair, untracked, its rectification checked
    (`ConfigError` naming the key of a bad option)."""
    from branchrange.core.cutpoints import CutPointConfig
    from branchrange.core.masks import MaskConfig
    from branchrange.core.pipeline import PipelineConfig

    return PipelineConfig(
        stereo=whole_frame_stereo(args),
        cutpoints=CutPointConfig(tracking=False),
        masks=MaskConfig(trunk_id=args.trunk_id),
        segmenter=segmenter_settings(args),
        check_pair=True,
    )


def _pipeline(args: argparse.Namespace, config: Any, size: tuple[int, int]) -> Any:
    """The pipeline the arguments describe (raises ValueError subclasses on bad camera input)."""
    from branchrange.core.pipeline import Pipeline
    from branchrange.core.settings_check import check_calibration, check_image_size, check_physical

    check_image_size(*size, name=f"{args.left}: image size")
    if args.calib is not None:
        from camera import load_calibration

        if args.doffs is not None:
            raise ValueError(
                "--doffs goes with --focal-px; with --calib the calibration sets it "
                "(a Middlebury calib.txt's doffs, otherwise 0)"
            )
        calibration = load_calibration(args.calib, args.resolution, size=size)
        check_calibration(calibration, size, str(args.calib))  # before the rectification maps are built
        return Pipeline(config, calibration=calibration, rectified=args.rectified)
    if args.baseline_m is None:
        raise ValueError("--focal-px needs --baseline-m (metres)")
    return Pipeline(
        config,
        focal_px=check_physical("focal_px", args.focal_px, "--focal-px"),
        baseline_m=check_physical("baseline_m", args.baseline_m, "--baseline-m"),
        doffs_px=args.doffs,
        principal_point=tuple(args.principal_point) if args.principal_point else None,
    )


def run(args: argparse.Namespace) -> int:
    """Read the pair, run the pipeline once, write JSON / overlay, print the table."""
    from branchrange.core.overlay import write_overlay
    from stereo.io import read_rgb

    try:
        config = _settings(args)  # bad options fail before any image is read
        left, right = read_rgb(args.left), read_rgb(args.right)
        pipeline = _pipeline(args, config, (left.shape[1], left.shape[0]))
        result = pipeline.process(left, right, mask=args.mask)
        if result.pair_check is not None and result.pair_check.status == "warning":
            print(f"branchrange estimate: warning: {result.pair_check.message}", file=sys.stderr)
        if result.masks.light is not None and result.masks.light.light != "normal":
            print(f"branchrange estimate: warning: {result.masks.light.message}", file=sys.stderr)
        if args.mask is not None and result.masks.instances == 0:
            raise ValueError(
                f"{args.mask}: the mask holds no branch instance (expected ids other than 0 "
                f"and the trunk id {args.trunk_id})"
            )
        text = json.dumps(result.to_json_dict(), indent=1)
        if args.json is not None:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(text + "\n", encoding="utf-8")
            print(branch_table(result))
            print(f"wrote {args.json}")
        else:
            print(text)
        if args.overlay is not None:
            artifacts = pipeline.last
            write_overlay(args.overlay, artifacts.left, result, artifacts.masks)
            print(f"wrote {args.overlay}", file=sys.stderr if args.json is None else sys.stdout)
    except (ValueError, OSError) as exc:  # every input/output error type of the chain is one of these
        print(f"branchrange estimate: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    return 0
