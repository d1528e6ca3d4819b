"""Writing synthetic scenes to disk in the VirtualTree layout, plus masks and branch geometry.

Under the output folder::

    left image/left_N.png     right image/right_N.png     (RGB 8-bit PNG)
    left depth/depth_N.exr    (depth in centimetres in the R channel, G and B NaN as UE5 writes them;
                               sky 65504, the fp16 maximum)
    masks/mask_N.png          (16-bit instance ids, see stereo.synth.truth)
    branches/branches_N.json  (camera f, B, size; per-branch geometry and truth cut point, metres)
    virtualtree_train.txt, virtualtree_val.txt, virtualtree_test.txt   (80/10/10)
    synth.json                (how the set was made: seed, camera, options)

Split files use the authors' line format, `left image/left_N.png left depth/depth_N.exr right
image/right_N.png`: three root-relative paths with spaces inside the folder names, which a
reader splits into six tokens and rejoins pairwise. Scene N is `render_scene(scene_seed(S, N))`.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from stereo.io import write_exr_depth, write_rgb
from stereo.progress import progress_bar
from stereo.synth.camera import SynthCamera
from stereo.synth.options import SynthOptions
from stereo.synth.render import SyntheticScene, render_scene
from stereo.synth.truth import LEAF_ID, TRUNK_ID, TWIG_ID

LEFT_DIR, RIGHT_DIR, DEPTH_DIR, MASK_DIR, BRANCH_DIR = "left image", "right image", "left depth", "masks", "branches"
SPLIT_FILE = "virtualtree_{}.txt"
SPLIT_FRACTIONS = {"train": 0.8, "val": 0.1, "test": 0.1}
#: Depth (cm) stored for sky, as in VirtualTree's UE5 renders (fp16 maximum).
SKY_DEPTH_CM = 65504.0
FORMAT = "emcstereo-synth/1"


class SynthWriteError(ValueError):
    """A dataset cannot be written with the given arguments (message names the argument and the fix)."""


@dataclass(frozen=True)
class DatasetSummary:
    """What `write_dataset` wrote: the root, how many scenes, the indices in each split."""

    root: Path
    scenes: int
    splits: dict[str, list[int]]


def scene_seed(dataset_seed: int, index: int) -> int:
    """Seed of scene `index` of a dataset drawn with `dataset_seed` (independent streams per scene)."""
    state = np.random.SeedSequence([int(dataset_seed), int(index)]).generate_state(2, dtype=np.uint32)
    return (int(state[0]) << 31) ^ int(state[1])


def split_indices(count: int, seed: int) -> dict[str, list[int]]:
    """Scene indices of the train/val/test splits (80/10/10, shuffled with `seed`, each sorted).

    Val and test get `round(0.1·count)` scenes each, at least one each when there are ≥ 3 scenes.
    """
    order = np.random.default_rng(seed).permutation(count)
    n_small = max(1, round(SPLIT_FRACTIONS["val"] * count)) if count >= 3 else 0
    parts = {"val": order[:n_small], "test": order[n_small : 2 * n_small], "train": order[2 * n_small :]}
    return {name: sorted(int(i) for i in parts[name]) for name in SPLIT_FRACTIONS}


def relative_paths(index: int) -> dict[str, str]:
    """Root-relative paths of scene `index`'s files."""
    return {
        "left": f"{LEFT_DIR}/left_{index}.png",
        "right": f"{RIGHT_DIR}/right_{index}.png",
        "depth": f"{DEPTH_DIR}/depth_{index}.exr",
        "mask": f"{MASK_DIR}/mask_{index}.png",
        "branches": f"{BRANCH_DIR}/branches_{index}.json",
    }


def split_line(index: int) -> str:
    """The authors' split-file line of scene `index`: left image, left depth, right image."""
    paths = relative_paths(index)
    return f"{paths['left']} {paths['depth']} {paths['right']}"


def depth_to_centimetres(depth_m: np.ndarray) -> np.ndarray:
    """VirtualTree's stored depth: float32 cm `H×W`, sky (non-finite) as 65504."""
    depth_cm = np.asarray(depth_m, dtype=np.float64) * 100.0
    return np.where(np.isfinite(depth_cm), np.minimum(depth_cm, SKY_DEPTH_CM), SKY_DEPTH_CM).astype(np.float32)


def write_mask(path: Path, mask: np.ndarray) -> None:
    """Write a uint16 `H×W` instance mask as a 16-bit grey PNG."""
    if mask.dtype != np.uint16 or mask.ndim != 2:
        raise SynthWriteError(f"cannot write {path}: expected a uint16 H×W mask, got {mask.dtype} {mask.shape}")
    ok, encoded = cv2.imencode(".png", mask)
    if not ok:
        raise SynthWriteError(f"cannot write {path}: OpenCV failed to encode the 16-bit PNG")
    path.write_bytes(encoded.tobytes())


def scene_record(scene: SyntheticScene, index: int, dataset_seed: int | None) -> dict[str, object]:
    """The branches JSON of one scene: camera, pose, id legend, files and per-branch truth."""
    return {
        "format": FORMAT,
        "index": index,
        "seed": scene.seed,
        "dataset_seed": dataset_seed,
        "camera": scene.camera.to_dict(),
        "frame": "rectified left camera; metres; x right, y down, z forward",
        "pose": scene.pose,
        "foliage": scene.foliage,
        "leaf_shape": scene.leaf_shape,
        "cut_offset_m": scene.cut_offset_m,
        "instance_ids": {
            "background": 0,
            "branches": "1..N (branch id)",
            "trunk": TRUNK_ID,
            "twig": TWIG_ID,
            "leaf": LEAF_ID,
        },
        "files": relative_paths(index),
        "branches": [branch.to_dict() for branch in scene.branches],
    }


def write_scene(
    root: Path, index: int, scene: SyntheticScene, *, dataset_seed: int | None = None, exr_pixel_type: str = "float"
) -> None:
    """Write one scene's images, EXR depth (cm), mask and branches JSON under `root` (folders must exist)."""
    paths = relative_paths(index)
    write_rgb(root / paths["left"], scene.left)
    write_rgb(root / paths["right"], scene.right)
    write_exr_depth(root / paths["depth"], depth_to_centimetres(scene.depth_m), pixel_type=exr_pixel_type)
    write_mask(root / paths["mask"], scene.instance_mask)
    (root / paths["branches"]).write_text(
        json.dumps(scene_record(scene, index, dataset_seed), indent=1) + "\n", encoding="utf-8"
    )


def _render_and_write(job: tuple[Path, int, int, SynthCamera, SynthOptions, str]) -> int:
    """Worker: render scene `index` of the dataset and write it; returns the index."""
    root, index, seed, camera, options, exr_pixel_type = job
    scene = render_scene(scene_seed(seed, index), camera, **dataclasses.asdict(options))
    write_scene(root, index, scene, dataset_seed=seed, exr_pixel_type=exr_pixel_type)
    return index


def _run_jobs(jobs: list[tuple], workers: int) -> Iterator[int]:
    """Render jobs in this process or in `workers` processes, yielding indices as they finish."""
    if workers <= 1:
        yield from map(_render_and_write, jobs)
        return
    with ProcessPoolExecutor(max_workers=workers) as pool:
        yield from pool.map(_render_and_write, jobs)


def write_dataset(
    out_dir: str | Path,
    scenes: int,
    seed: int,
    width: int,
    height: int,
    *,
    camera: SynthCamera | None = None,
    options: SynthOptions | None = None,
    exr_pixel_type: str = "float",
    workers: int = 1,
    progress: bool = True,
) -> DatasetSummary:
    """Render `scenes` scenes (ZED Mini rig scaled to `width`×`height` unless `camera` is given) into `out_dir`.

    The same arguments give byte-identical files. `exr_pixel_type` 'float' keeps depth exact;
    'half' stores fp16 like the UE5 originals. `workers` > 1 renders in that many processes.
    """
    if scenes < 1:
        raise SynthWriteError(f"scenes must be at least 1, got {scenes}")
    camera = camera if camera is not None else SynthCamera.zed_mini(width, height)
    if (camera.width, camera.height) != (width, height):
        raise SynthWriteError(f"camera size {camera.width}×{camera.height} differs from the requested {width}×{height}")
    if exr_pixel_type not in ("float", "half"):
        raise SynthWriteError(f"exr_pixel_type must be 'float' or 'half', got {exr_pixel_type!r}")
    options = options if options is not None else SynthOptions()
    root = Path(out_dir)
    for folder in (LEFT_DIR, RIGHT_DIR, DEPTH_DIR, MASK_DIR, BRANCH_DIR):
        (root / folder).mkdir(parents=True, exist_ok=True)
    jobs = [(root, index, seed, camera, options, exr_pixel_type) for index in range(scenes)]
    for _ in progress_bar(
        iterable=_run_jobs(jobs, workers), total=scenes, desc="synth scenes", unit="scene", disable=not progress
    ):
        pass
    splits = split_indices(scenes, seed)
    for name, indices in splits.items():
        (root / SPLIT_FILE.format(name)).write_text("".join(split_line(i) + "\n" for i in indices), encoding="utf-8")
    meta = {
        "format": FORMAT,
        "seed": seed,
        "scenes": scenes,
        "camera": camera.to_dict(),
        "options": dataclasses.asdict(options),
        "exr_pixel_type": exr_pixel_type,
        "splits": {name: len(indices) for name, indices in splits.items()},
    }
    (root / "synth.json").write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    return DatasetSummary(root, scenes, splits)
