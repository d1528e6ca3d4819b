"""Exact ray-cast rendering of a synthetic tree scene from both cameras of a rectified rig.

Images: `supersample²` rays per pixel, z-buffered over every surface, box-filtered down, then
auto-exposed (the same gain for both views), given small per-view gain differences and sensor
noise. Ground truth: one ray through each left pixel centre gives depth Z (m), the instance id
of the surface it hits, and disparity `f·B/Z` — exact, not interpolated.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from stereo.synth.camera import RayGrid, SynthCamera
from stereo.synth.cones import ConeBatch
from stereo.synth.leaves import LeafBatch
from stereo.synth.options import SynthOptions
from stereo.synth.primitives import Batch, Lighting
from stereo.synth.scene import SceneDescription, build_scene
from stereo.synth.sky import Sky
from stereo.synth.truth import BranchTruth

_LUMA = np.array([0.299, 0.587, 0.114])


@dataclass(frozen=True)
class SyntheticScene:
    """A rendered stereo pair with its exact ground truth (left view is the reference).

    - `left`, `right`: RGB `uint8` `H×W×3`.
    - `disparity`: float32 `H×W` px, `f·B/Z`; 0 on sky.
    - `depth_m`: float32 `H×W` metres (z, not range); inf on sky.
    - `instance_mask`: uint16 `H×W`; ids as in `stereo.synth.truth`.
    - `branches`: the pruning-target branches, ids 1..N, in the left camera frame.
    - `pose`, `foliage`, `leaf_shape`: the classes drawn for the scene ('auto' resolved).
    """

    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray
    depth_m: np.ndarray
    instance_mask: np.ndarray
    branches: list[BranchTruth]
    camera: SynthCamera
    seed: int
    pose: str
    foliage: str
    leaf_shape: str
    cut_offset_m: float


def scene_batches(scene: SceneDescription, camera: SynthCamera) -> list[Batch]:
    """All surfaces of a scene in casting order: cones and leaves (near to far inside), then the planes."""
    return [ConeBatch(scene.cones, camera), LeafBatch(scene.leaves, scene.leaf_detail), *scene.layers]


def rasterise(
    batches: Sequence[Batch], rays: RayGrid, light: Lighting | None, sky: Sky | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Z-buffer the surfaces over a ray grid.

    Returns depth (float64 `Hs×Ws`, m, inf where nothing is hit), instance ids (uint16 `Hs×Ws`)
    and, when `light` and `sky` are given, colour (float32 `Hs×Ws×3`, about [0, 1]).
    """
    shape = rays.shape
    depth = np.full(shape, np.inf)
    ids = np.zeros(shape, dtype=np.uint16)
    colour = np.zeros((shape[0] * shape[1], 3), dtype=np.float32) if light is not None else None
    flat_depth, flat_ids = depth.reshape(-1), ids.reshape(-1)
    sample_angle = 1.0 / (rays.focal_px * rays.samples)
    for batch in batches:
        for hit in batch.hits(rays, depth):
            flat_depth[hit.index] = hit.depth
            flat_ids[hit.index] = batch.instance_ids(hit.part)
            if colour is not None:
                rows, cols = np.divmod(hit.index, shape[1])
                points = rays.origin[None, :] + hit.depth[:, None] * _directions(rays, rows, cols)
                colour[hit.index] = light.hazed(batch.shade(points, hit.part, light, sample_angle), points)
    if colour is not None:
        rows, cols = np.divmod(np.flatnonzero(~np.isfinite(flat_depth)), shape[1])
        colour[rows * shape[1] + cols] = sky.colour(_directions(rays, rows, cols))
        colour = colour.reshape(*shape, 3)
    return depth, ids, colour


def _directions(rays: RayGrid, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Ray directions `(N, 3)` (z = 1) of the given samples."""
    return np.stack([rays.dx[cols], rays.dy[rows], np.ones(rows.size)], axis=1)


def _box_filter(colour: np.ndarray, samples: int) -> np.ndarray:
    """Average `samples × samples` blocks: `(H·s, W·s, 3)` → `(H, W, 3)`."""
    hs, ws, _ = colour.shape
    return colour.reshape(hs // samples, samples, ws // samples, samples, 3).mean(axis=(1, 3))


def auto_gain(image: np.ndarray, target: float) -> float:
    """The exposure gain (0.5–3) that brings the mean luma of linear `image` (`H×W×3`) to `target` (about 0.4)."""
    luma = float((image.reshape(-1, 3).mean(axis=0) * _LUMA).sum())
    return float(np.clip(target / max(luma, 1e-3), 0.5, 3.0))


def develop(
    images: Sequence[np.ndarray], gain: float, options: SynthOptions, rng: np.random.Generator
) -> list[np.ndarray]:
    """Linear colour views (float32 `H×W×3`) → uint8 with one `gain`, per-view gain jitter and sensor noise."""
    out = []
    for image in images:
        view_gain = 1.0 + rng.uniform(-options.view_gain_jitter, options.view_gain_jitter, 3) / 2
        levels = np.clip(image * np.float32(gain) * view_gain.astype(np.float32), 0.0, 1.0) * np.float32(255.0)
        if options.noise_std > 0:
            levels += options.noise_std * rng.standard_normal(levels.shape, dtype=np.float32)
        out.append(np.clip(np.rint(levels), 0, 255).astype(np.uint8))
    return out


def with_visibility(branches: Sequence[BranchTruth], ids: np.ndarray) -> list[BranchTruth]:
    """Branch truth completed with pixel counts and whether the mask shows each cut point.

    A cut point is visible when it lies in front of the camera, its `cut_pixel` rounds to a pixel
    of the image and the mask `ids` (uint16 `H×W`) holds its branch's id there.
    """
    counts = np.bincount(ids.ravel(), minlength=int(max((b.id for b in branches), default=0)) + 1)
    height, width = ids.shape
    done = []
    for branch in branches:
        x, y = (int(round(c)) if np.isfinite(c) else -1 for c in branch.cut_pixel)
        visible = branch.cut_point_m[2] > 0 and 0 <= x < width and 0 <= y < height and int(ids[y, x]) == branch.id
        done.append(dataclasses.replace(branch, cut_visible=visible, mask_pixels=int(counts[branch.id])))
    return done


@dataclass(frozen=True)
class RenderedViews:
    """Both views of a scene before exposure, with the left view's exact truth.

    - `left`, `right`: box-filtered linear colour, float32 `H×W×3` (about [0, 1]).
    - `depth`: left depth Z, float64 `H×W` m (inf on sky), from the ray through each pixel centre.
    - `ids`: left instance ids, uint16 `H×W` (see `stereo.synth.truth`).
    - `right_depth`: right depth, float64 `H×W` m: the pixel-centre ray's at `supersample` 1, else the
      nearest of each pixel's samples (what motion blur needs, not truth).
    """

    left: np.ndarray
    right: np.ndarray
    depth: np.ndarray
    ids: np.ndarray
    right_depth: np.ndarray


def render_views(scene: SceneDescription, camera: SynthCamera, supersample: int, threads: int) -> RenderedViews:
    """Ray-cast both views of `scene` (given in the left camera frame) with `supersample²` rays per pixel.

    At `supersample` 1 the left colour pass's rays are the pixel centres, so its depth and ids are
    the truth; otherwise a third pass casts the pixel centres. The passes share nothing mutable, and
    numpy and OpenCV release the GIL in their loops, so they run in `threads` threads.
    """
    batches = scene_batches(scene, camera)

    def colour_view(view: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Depth and ids at the samples, box-filtered linear colour (float32 `H×W×3`) of one view."""
        depth, ids, colour = rasterise(batches, RayGrid.for_view(camera, view, supersample), scene.lighting, scene.sky)
        return depth, ids, _box_filter(colour, supersample)

    with ThreadPoolExecutor(max_workers=threads) as pool:
        truth = (
            pool.submit(rasterise, batches, RayGrid.for_view(camera, "left", 1), None, None)
            if supersample > 1
            else None
        )
        (left_depth, left_ids, left), (right_depth, _, right) = pool.map(colour_view, ("left", "right"))
        depth, ids, _ = truth.result() if truth is not None else (left_depth, left_ids, None)
    if supersample > 1:
        right_depth = right_depth.reshape(camera.height, supersample, camera.width, supersample).min(axis=(1, 3))
    return RenderedViews(left, right, depth, ids, right_depth)


def render_scene(seed: int, camera: SynthCamera | None = None, **options: object) -> SyntheticScene:
    """Render the scene drawn from `seed` with `camera` (default ZED Mini at 1280×720).

    Keyword options are the fields of `SynthOptions` (e.g. `cut_offset_m=0.05`, `supersample=2`,
    `noise_std=0`); the same seed, camera and options give identical arrays.
    """
    opts = SynthOptions.from_mapping(dict(options))
    camera = camera if camera is not None else SynthCamera.zed_mini(1280, 720)
    rng = np.random.default_rng(seed)
    scene = build_scene(rng, camera, opts)
    views = render_views(scene, camera, opts.supersample, opts.threads)
    left, right = develop([views.left, views.right], auto_gain(views.left, scene.exposure_target), opts, rng)
    depth_m = views.depth.astype(np.float32)
    return SyntheticScene(
        left,
        right,
        camera.disparity_from_depth(views.depth),
        depth_m,
        views.ids,
        with_visibility(scene.branches, views.ids),
        camera,
        int(seed),
        scene.pose,
        scene.foliage,
        scene.leaf_shape,
        opts.cut_offset_m,
    )
