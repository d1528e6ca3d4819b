"""`emcstereo synth`: render synthetic stereo tree-branch scenes in the VirtualTree layout, or a preview;
with `--randomized`, scenes of the randomized domain (`stereo.synth.randomized`) and a contact sheet."""

from __future__ import annotations

import argparse
import re
import time
from pathlib import Path

import cv2

from stereo.io import StereoIOError, write_rgb
from stereo.synth import SynthCamera, SynthOptions, render_scene
from stereo.synth.options import FOLIAGE, LEAF_SHAPES, POSES
from stereo.synth.preview import preview_image
from stereo.synth.randomized import RandomizedSwitches, render_randomized
from stereo.synth.randomized_output import randomized_contact_sheet, write_randomized
from stereo.synth.writer import scene_seed, write_dataset

#: Largest side accepted (px): a 2×2-supersampled 4096² render already needs a few GB of memory.
MAX_SIDE_PX = 4096


def parse_size(text: str) -> tuple[int, int]:
    """'640x360' → (640, 360); argparse reports anything else with the expected form."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", text)
    if not match:
        raise argparse.ArgumentTypeError(f"size {text!r} is not WIDTHxHEIGHT in pixels, e.g. 640x360")
    width, height = int(match.group(1)), int(match.group(2))
    if width < 64 or height < 64:
        raise argparse.ArgumentTypeError(f"size {text!r} is too small: width and height must be at least 64 px")
    if width > MAX_SIDE_PX or height > MAX_SIDE_PX:
        raise argparse.ArgumentTypeError(
            f"size {text!r} is too large: width and height must be at most {MAX_SIDE_PX} px"
        )
    return width, height


def _options(args: argparse.Namespace) -> SynthOptions:
    """The generator options the flags ask for; an out-of-range value exits with its message."""
    try:
        return SynthOptions(
            cut_offset_m=args.cut_offset,
            supersample=args.supersample,
            pose=args.pose,
            foliage=args.foliage,
            leaf_shape=args.leaf_shape,
            noise_std=args.noise,
            background_trees=not args.no_background_trees,
            orchard_hardware=args.orchard_hardware,
        )
    except ValueError as exc:
        raise SystemExit(f"emcstereo synth: {exc}") from exc


def _run(args: argparse.Namespace) -> int:
    """Write the dataset and/or the preview the flags ask for; exit with a message naming a bad flag or path."""
    if args.out is None and args.preview is None:
        raise SystemExit("emcstereo synth: give --out DIR (a dataset), --preview PNG (a picture), or both")
    if args.scenes < 1 or args.workers < 1 or args.preview_scenes < 1:
        raise SystemExit(
            f"emcstereo synth: --scenes ({args.scenes}), --workers ({args.workers}) and "
            f"--preview-scenes ({args.preview_scenes}) must be at least 1"
        )
    if args.preview is not None and not cv2.haveImageWriter(str(args.preview)):
        raise SystemExit(
            f"emcstereo synth: --preview {args.preview}: no image format for the extension "
            f"{args.preview.suffix!r}; use .png"
        )
    width, height = args.size
    camera = SynthCamera.zed_mini(width, height)
    if args.randomized:
        return _run_randomized(args, camera)
    options = _options(args)
    if args.out is not None:
        start = time.perf_counter()
        try:
            summary = write_dataset(
                args.out,
                args.scenes,
                args.seed,
                width,
                height,
                camera=camera,
                options=options,
                exr_pixel_type="half" if args.exr_half else "float",
                workers=args.workers,
                progress=not args.quiet,
            )
        except OSError as exc:
            raise SystemExit(f"emcstereo synth: cannot write the dataset under --out {args.out}: {exc}") from exc
        seconds = time.perf_counter() - start
        counts = ", ".join(f"{name} {len(indices)}" for name, indices in summary.splits.items())
        print(
            f"wrote {summary.scenes} scenes ({width}×{height}, f = {camera.focal_px:g} px, B = {camera.baseline_m} m) "
            f"to {summary.root} in {seconds:.1f} s ({seconds / summary.scenes:.2f} s/scene); splits: {counts}"
        )
    if args.preview is not None:
        count = min(args.preview_scenes, args.scenes)
        scenes = [render_scene(scene_seed(args.seed, i), camera, **vars(options)) for i in range(count)]
        try:
            args.preview.parent.mkdir(parents=True, exist_ok=True)
            write_rgb(args.preview, preview_image(scenes))
        except (OSError, StereoIOError) as exc:
            raise SystemExit(f"emcstereo synth: cannot write --preview {args.preview}: {exc}") from exc
        print(
            f"wrote preview of scenes 0..{count - 1} to {args.preview} "
            "(left | right | disparity | mask, cut points ringed)"
        )
    return 0


def _run_randomized(args: argparse.Namespace, camera: SynthCamera) -> int:
    """`--randomized`: write the samples to `--out` and/or a contact sheet of the first `--preview-scenes`."""
    count = args.scenes if args.out is not None else min(args.scenes, args.preview_scenes)
    seeds = [args.seed + index for index in range(count)]
    if not 1 <= args.supersample <= 4:
        raise SystemExit(f"emcstereo synth: --supersample must be 1 to 4 rays per pixel side, got {args.supersample}")
    start = time.perf_counter()
    if args.out is not None:
        try:
            samples = write_randomized(args.out, seeds, camera, RandomizedSwitches(), args.supersample)
        except OSError as exc:
            raise SystemExit(f"emcstereo synth: cannot write the samples under --out {args.out}: {exc}") from exc
        seconds = time.perf_counter() - start
        print(
            f"wrote {count} randomized scenes (seeds {seeds[0]}..{seeds[-1]}) to {args.out} in {seconds:.1f} s "
            f"({seconds / count:.2f} s/scene)"
        )
    else:
        samples = [render_randomized(seed, camera, RandomizedSwitches(), args.supersample) for seed in seeds]
    if args.preview is not None:
        shown = samples[: args.preview_scenes]
        try:
            args.preview.parent.mkdir(parents=True, exist_ok=True)
            write_rgb(args.preview, randomized_contact_sheet(shown))
        except (OSError, StereoIOError) as exc:
            raise SystemExit(f"emcstereo synth: cannot write --preview {args.preview}: {exc}") from exc
        print(f"wrote a contact sheet of {len(shown)} randomized scenes to {args.preview} (left | mask)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add `synth` to the `emcstereo` command."""
    parser = sub.add_parser(
        "synth",
        help="render synthetic tree-branch stereo scenes (VirtualTree layout) or a preview",
        description=__doc__,
    )
    parser.add_argument("--out", type=Path, help="dataset folder to write (created if needed)")
    parser.add_argument("--scenes", type=int, default=10, help="number of scenes (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="dataset seed; same seed, same files (default 0)")
    parser.add_argument("--size", type=parse_size, default=(640, 360), help="WIDTHxHEIGHT in px (default 640x360)")
    parser.add_argument("--preview", type=Path, help="write a PNG: left | right | disparity | mask per scene")
    parser.add_argument("--preview-scenes", type=int, default=3, help="scenes in the preview (default 3)")
    parser.add_argument("--supersample", type=int, default=2, help="rays per pixel side for images (default 2)")
    parser.add_argument(
        "--cut-offset",
        type=float,
        default=0.05,
        help="truth cut point: metres from the branch base along its axis (default 0.05)",
    )
    parser.add_argument("--pose", choices=POSES, default="auto", help="camera pitch class (default: drawn per scene)")
    parser.add_argument("--foliage", choices=FOLIAGE, default="auto", help="leaves (default: drawn per scene)")
    parser.add_argument(
        "--leaf-shape",
        choices=LEAF_SHAPES,
        default="broad",
        help="broad leaf blades, conifer needle clusters, or auto: drawn per scene (default broad)",
    )
    parser.add_argument("--noise", type=float, default=1.0, help="sensor noise std in grey levels (default 1)")
    parser.add_argument("--no-background-trees", action="store_true", help="leave out mid-ground trees")
    parser.add_argument(
        "--orchard-hardware",
        action="store_true",
        help="add trellis wires, posts, a stake and painted rods around the tree (background, not targets)",
    )
    parser.add_argument(
        "--randomized",
        action="store_true",
        help="scenes of the randomized domain (every factor drawn per scene): --out gets randomized_<seed>.npz "
        "and .json per scene, --preview a contact sheet; seeds are --seed, --seed+1, …",
    )
    parser.add_argument("--exr-half", action="store_true", help="store depth as fp16 like the UE5 originals")
    parser.add_argument("--workers", type=int, default=1, help="render in this many processes (default 1)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=_run)
