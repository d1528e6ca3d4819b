"""Training data for `BranchNet`: synthetic scenes rendered here, their SGBM disparity and per-pixel classes.

A sample is one `stereo.synth.render_scene` frame (its seed decides everything) at the rendering size:
- `left` `uint8 H×W×3` RGB, `disparity` `float16 H×W` px from the project's SGBM stage (what the
  network sees at run time, with its holes and fattened edges — not the exact disparity);
- `classes` `uint8 H×W`: `BACKGROUND`, `TRUNK`, `BRANCH`, or `IGNORE` for twigs (woody like a branch
  but never a pruning target: neither answer is penalised);
- `instances` `uint16 H×W`: the renderer's instance mask (branches 1..K, twigs/leaves/trunk ids).

Samples are cached as compressed `.npz` files so training, its resumption and the benchmark's
held-out scenes never render the same seed twice; the randomized domain's (`render_randomized_sample`) under
names of their own, keyed by seed, size and switches. Training seeds start at 1; the segmenter
benchmark's held-out seeds start at 50,000 (`TRAIN_SEED_LIMIT` keeps them apart).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from itertools import repeat
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from stereo.synth.randomized import RandomizedSwitches

BACKGROUND, TRUNK, BRANCH, IGNORE = 0, 1, 2, 255
#: renderer ids (`stereo.synth`): trunk, twigs, leaves; 1..K are branches, 0 everything else
TRUNK_ID, TWIG_ID, LEAF_ID = 65535, 65534, 65533
#: training seeds stay below this; held-out benchmark scenes start here
TRAIN_SEED_LIMIT = 50_000


def classes_from_instances(instances: np.ndarray) -> np.ndarray:
    """`uint8 H×W` class map of a renderer instance mask `uint16 H×W` (see the module docstring)."""
    classes = np.full(instances.shape, BACKGROUND, dtype=np.uint8)
    classes[(instances > 0) & (instances < LEAF_ID)] = BRANCH
    classes[instances == TRUNK_ID] = TRUNK
    classes[instances == TWIG_ID] = IGNORE
    return classes


def render_sample(
    seed: int, size: tuple[int, int] = (640, 360), max_disp: int = 128, hardware: bool = False
) -> dict[str, np.ndarray]:
    """One training sample (see the module docstring) of scene `seed` at `size` (width, height) px; `hardware`:
    with orchard hardware around the tree (`SynthOptions.orchard_hardware`: wires, posts, stakes, rods)."""
    from stereo.backends import make_backend
    from stereo.synth import SynthCamera, render_scene

    scene = render_scene(seed, SynthCamera.zed_mini(*size), leaf_shape="auto", threads=1, orchard_hardware=hardware)
    stereo = make_backend("sgbm", max_disp=max_disp).compute(scene.left, scene.right)
    return {
        "left": scene.left,
        "disparity": stereo.disparity.astype(np.float16),
        "classes": classes_from_instances(scene.instance_mask),
        "instances": scene.instance_mask,
    }


def render_randomized_sample(
    seed: int, size: tuple[int, int] = (640, 360), switches: RandomizedSwitches | None = None
) -> dict[str, np.ndarray]:
    """One training sample (the format of `render_sample`) of the randomized domain's scene `seed` at `size`
    (width, height) px: `stereo.synth.randomized`, every factor drawn per scene unless `switches` holds it."""
    from stereo.synth import SynthCamera
    from stereo.synth.randomized import render_randomized

    scene = render_randomized(seed, SynthCamera.zed_mini(*size), switches)
    return {
        "left": scene.left,
        "disparity": scene.disparity.astype(np.float16),
        "classes": classes_from_instances(scene.instances),
        "instances": scene.instances,
    }


def sample_path(folder: Path, seed: int, hardware: bool = False) -> Path:
    """Where `cached_sample` keeps the training sample of `seed` (with orchard hardware when `hardware`)."""
    return folder / f"sample_{_hardware_tag(hardware)}{seed:06d}.npz"


def cached_sample(
    folder: Path, seed: int, size: tuple[int, int] = (640, 360), hardware: bool = False
) -> dict[str, np.ndarray]:
    """The sample of `seed` (with orchard hardware when `hardware`) from `folder`, rendered and stored there first
    when absent."""
    return _cached(sample_path(folder, seed, hardware), lambda: render_sample(seed, size, hardware=hardware))


def randomized_sample_path(
    folder: Path, seed: int, size: tuple[int, int] = (640, 360), switches: RandomizedSwitches | None = None
) -> Path:
    """Where `cached_randomized_sample` keeps the randomized domain's sample of `seed`: keyed by the seed, the size
    and a digest of the switches' values (`RandomizedSwitches`, the default ones when None), so neither the
    generator's scenes nor those of other switches or sizes ever share a file."""
    from stereo.synth.randomized import RandomizedSwitches

    values = json.dumps(dataclasses.asdict(switches or RandomizedSwitches()), sort_keys=True)
    digest = hashlib.sha256(values.encode()).hexdigest()[:12]
    return folder / f"randomized_{digest}_{size[0]}x{size[1]}_{seed:06d}.npz"


def cached_randomized_sample(
    folder: Path, seed: int, size: tuple[int, int] = (640, 360), switches: RandomizedSwitches | None = None
) -> dict[str, np.ndarray]:
    """`render_randomized_sample(seed, size, switches)` from `folder`, rendered and stored there first when
    absent (`randomized_sample_path`)."""
    path = randomized_sample_path(folder, seed, size, switches)
    return _cached(path, lambda: render_randomized_sample(seed, size, switches))


#: the domains a training scene comes from: `render_sample`'s scenes (with orchard hardware where asked) or
#: `render_randomized_sample`'s (every factor drawn per scene); `training.TRAINING_DOMAINS` trains on one or both
DOMAINS = ("generator", "randomized")


def training_sample_path(folder: Path, seed: int, hardware: bool = False, domain: str = "generator") -> Path:
    """Where `training_sample` keeps a scene of `domain` (`DOMAINS`) at 640×360."""
    return randomized_sample_path(folder, seed) if domain == "randomized" else sample_path(folder, seed, hardware)


def training_sample(
    folder: Path, seed: int, hardware: bool = False, domain: str = "generator"
) -> dict[str, np.ndarray]:
    """The 640×360 training sample of scene `seed` of `domain` (`DOMAINS`; `hardware` only counts for the
    generator's), cached in `folder`."""
    return (
        cached_randomized_sample(folder, seed)
        if domain == "randomized"
        else cached_sample(folder, seed, hardware=hardware)
    )


def _cached(path: Path, render: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The arrays stored at `path`, or `render()`'s, stored there first (`save_atomically`)."""
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    sample = render()
    save_atomically(path, sample)
    return sample


def render_samples(folder: Path, seeds: Sequence[tuple[int, bool]], workers: int, domain: str = "generator") -> int:
    """Render into `folder` the training samples of `seeds` — (seed, with orchard hardware) pairs of `domain`
    (`DOMAINS`) — that are not cached there yet, in `workers` processes (`spawned_pool`); how many were rendered.

    Why: training draws its scenes one by one and would render each on first use, ~0.7 s a scene on one
    core (1,200 scenes: ~15 min of a recipe that must fit in 2 hours; a randomized scene takes ~2 s). A
    sample depends on its seed alone, so the cache is the one a single process writes."""
    missing = [
        (seed, hardware)
        for seed, hardware in seeds
        if not training_sample_path(folder, seed, hardware, domain).is_file()
    ]
    if workers > 1 and len(missing) > 1:
        with spawned_pool(min(workers, len(missing))) as pool:
            list(pool.map(_render_into, repeat(folder), *zip(*missing), repeat(domain), chunksize=4))
    else:
        for seed, hardware in missing:
            _render_into(folder, seed, hardware, domain)
    return len(missing)


def _render_into(folder: Path, seed: int, hardware: bool, domain: str = "generator") -> None:
    """`training_sample` without handing the arrays back (a worker's result crosses a pipe)."""
    training_sample(folder, seed, hardware, domain)


def spawned_pool(workers: int) -> ProcessPoolExecutor:
    """`workers` spawned processes, each with one OpenCV thread: the workers share the cores, and a spawned
    process inherits none of the parent's threads (onnxruntime's, torch's), which a fork would copy mid-state."""
    return ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_one_opencv_thread)


def _one_opencv_thread() -> None:
    """A worker's OpenCV runs on one thread (SGBM's disparity does not depend on it)."""
    import cv2

    cv2.setNumThreads(1)


def save_atomically(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """`arrays` as a compressed `.npz` at `path` (its folder made), written under a name of this process's own
    and then renamed: a killed render never leaves a half-written file, and two processes rendering one seed
    (a benchmark beside a calibration) never write into one file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
    np.savez_compressed(partial, **arrays)
    partial.replace(path)


def _hardware_tag(hardware: bool) -> str:
    """The part of a cached file's name that keeps scenes with orchard hardware apart from plain ones."""
    return "hw_" if hardware else ""


def _domain_tag(domain: str) -> str:
    """The part of a cached file's name that keeps scenes of another domain than the park apart."""
    return "" if domain == "park" else f"{domain}_"


def _size_tag(width: int, height: int) -> str:
    """The part of a cached file's name that keeps scenes of another size than 640×360 apart."""
    return "" if (width, height) == (640, 360) else f"{width}x{height}_"


#: the SGBM disparity range (px at 640×360) of the scenes the segmenter is scored and calibrated on
EVALUATION_MAX_DISP = 192


def evaluation_max_disp(width: int) -> int:
    """The SGBM disparity range (px) of an evaluation scene `width` px wide: `EVALUATION_MAX_DISP` at 640 px,
    as many times more as the frame is wider."""
    return EVALUATION_MAX_DISP * max(1, round(width / 640))


def evaluation_scene(
    seed: int, cache: Path | None, size: tuple[int, int] = (640, 360), hardware: bool = False, domain: str = "park"
) -> dict:
    """A scene as the segmenter is scored on it: the default renderer options at `size` (plus orchard hardware
    when `hardware`; of `domain`, `SynthOptions.domain`), SGBM over `evaluation_max_disp(width)` px, truth cut
    points. Keys: left, right, disparity (exact), mask (renderer ids), sgbm, sgbm_conf, camera (f px, B m, cx,
    cy), truth (list of {"cut_point_m", "cut_visible"}). Cached in `cache` when given (a cached scene from
    before the right image was kept is rendered again).

    The same seed at another size is the same scene in most cases but not all: the renderer's random draws
    depend on what is visible in pixels, so about one seed in four (55 of the 240 held-out ones) places its
    branches elsewhere."""
    tag = _domain_tag(domain) + _hardware_tag(hardware) + _size_tag(size[0], size[1])
    path = cache / f"scene_{tag}{seed}.npz" if cache is not None else None
    if path is not None and path.is_file():
        with np.load(path, allow_pickle=False) as data:
            scene = {k: data[k] for k in data.files}
        if "right" in scene:
            scene["truth"] = json.loads(str(scene["truth"]))
            return scene
    from stereo.backends import make_backend
    from stereo.synth import SynthCamera, render_scene

    rendered = render_scene(seed, SynthCamera.zed_mini(*size), orchard_hardware=hardware, domain=domain)
    stereo = make_backend("sgbm", max_disp=evaluation_max_disp(size[0])).compute(rendered.left, rendered.right)
    cam = rendered.camera
    truth = [{"cut_point_m": list(b.cut_point_m), "cut_visible": bool(b.cut_visible)} for b in rendered.branches]
    scene = {
        "left": rendered.left,
        "right": rendered.right,
        "disparity": rendered.disparity,
        "mask": rendered.instance_mask,
        "sgbm": stereo.disparity,
        "sgbm_conf": stereo.confidence,
        "camera": np.array([cam.focal_px, cam.baseline_m, cam.cx, cam.cy]),
        "truth": json.dumps(truth),
    }
    if path is not None:
        save_atomically(path, scene)
    scene["truth"] = truth
    return scene


def scene_in_light(scene: dict, seed: int, change: str, cache: Path | None, hardware: bool = False) -> dict:
    """`evaluation_scene(seed, ...)`'s `scene` under the named change of light (`light_changes.LIGHT_CHANGES`):
    both images changed alike (the noise seeded by the seed and the change's name, so a run repeats), SGBM over
    `evaluation_max_disp(width)` px computed again; the other keys as they were. Cached in `cache` when given."""
    from branchrange.learning.light_changes import changed_light

    height, width = scene["left"].shape[:2]
    tag = _hardware_tag(hardware) + _size_tag(width, height)
    path = cache / f"light_{change}_{tag}{seed}.npz" if cache is not None else None
    if path is not None and path.is_file():
        with np.load(path, allow_pickle=False) as data:
            return {**scene, **{k: data[k] for k in data.files}}
    from stereo.backends import make_backend

    rng = np.random.default_rng([seed, *change.encode()])
    left, right = (changed_light(scene[side], change, rng) for side in ("left", "right"))
    stereo = make_backend("sgbm", max_disp=evaluation_max_disp(width)).compute(left, right)
    changed = {"left": left, "right": right, "sgbm": stereo.disparity, "sgbm_conf": stereo.confidence}
    if path is not None:
        save_atomically(path, changed)
    return {**scene, **changed}
