"""The instance step's kernels, rewritten to work on a frame's foreground pixels or their bounding box, against
the frame-wide implementations they replaced (kept here, named `reference_*`, as the definition of the result):
`foreground_depth_edges`, `straight_pieces_of`, `straight_pieces` (its tests in blocks of points),
`_branch_support` and `trunk_gap_m`, on random masks and depths and on rendered scenes (branch and trunk pixels
of the renderer's own instance masks)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from branchrange.core.geometry import StereoGeometry, disparity_to_depth, valid_disparity
from branchrange.core.segmentation.pieces import (
    BLOCK_POINTS,
    LOCAL_WIDTH_PX,
    PIECE_MIN_DISPARITY_PX,
    bridged_region_of,
    bridged_regions,
    padded_box,
    straight_pieces,
    straight_pieces_of,
)
from branchrange.core.segmentation.segmenter import foreground_depth_edges
from branchrange.core.segmentation.trunk import TRUNK_DEPTH_TOLERANCE, _branch_support, trunk_gap_m
from stereo.synth import TRUNK_ID, SynthCamera, is_branch_id, render_scene

GEOMETRY = StereoGeometry(focal_px=500.0, baseline_m=0.063, cx=240.0, cy=135.0)


def reference_depth_edges(depth: np.ndarray, ratio: float) -> np.ndarray:
    """The frame-wide depth edges as the instance step computed them before (every pixel against the one
    below and the one to the right, the farther of a pair marked)."""
    edges = np.zeros(depth.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        for a, b, edges_a, edges_b in (
            (depth[:-1], depth[1:], edges[:-1], edges[1:]),
            (depth[:, :-1], depth[:, 1:], edges[:, :-1], edges[:, 1:]),
        ):
            jump = np.abs(a - b) > ratio * np.minimum(a, b)
            far_is_a = a > b
            edges_a |= jump & far_is_a
            edges_b |= jump & ~far_is_a
    return edges


def reference_straight_pieces_of(
    mask: np.ndarray,
    min_px: int,
    rng: np.random.Generator,
    bridge_px: int = 0,
    disparity: np.ndarray | None = None,
    disparity_ratio: float = 0.0,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """`straight_pieces_of` as it was: distances, bridged regions and disparities over the whole frame."""
    inside = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3)
    local_radius = cv2.dilate(inside, np.ones((2 * LOCAL_WIDTH_PX + 1,) * 2, np.uint8))
    count, components = bridged_regions(mask, bridge_px)
    pixels = np.flatnonzero(mask)
    region = components.ravel()[pixels]
    pixels = pixels[np.argsort(region, kind="stable")]
    ends = np.cumsum(np.bincount(region, minlength=count))
    for i in range(1, count):
        if ends[i] - ends[i - 1] < min_px:
            continue
        v, u = np.divmod(pixels[ends[i - 1] : ends[i]], mask.shape[1])
        band = np.maximum(1.5, 1.2 * local_radius[v, u])
        known = None
        if disparity is not None and disparity_ratio > 0:
            own = disparity[v, u]
            known = np.where(np.isfinite(own) & (own > 0), own, np.nan)
        gap = max(4.0, 2.0 * bridge_px + 1.0)
        for piece in straight_pieces(
            u, v, band, min_px, rng, min_gap_px=gap, disparity=known, disparity_ratio=disparity_ratio
        ):
            yield u[piece], v[piece]


def reference_branch_support(
    components: np.ndarray,
    trunk_pixels: np.ndarray,
    trunk_region: np.ndarray,
    depths: np.ndarray,
    branch_px: np.ndarray,
    depth: np.ndarray,
    geometry: StereoGeometry,
    max_gap_m: float,
) -> np.ndarray:
    """`_branch_support` as it was: the distance transform (with labels) over the whole frame."""
    gap_px, nearest = cv2.distanceTransformWithLabels(
        (components == 0).astype(np.uint8), cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL
    )
    region_of = np.zeros(int(nearest.max()) + 1, dtype=np.int64)
    region_of[nearest.ravel()[trunk_pixels]] = trunk_region
    branch = np.flatnonzero(branch_px & np.isfinite(depth))
    region = region_of[nearest.ravel()[branch]]
    z = depth.ravel()[branch]
    close = gap_px.ravel()[branch] * z / geometry.focal_px <= max_gap_m
    with np.errstate(invalid="ignore"):
        same_depth = np.abs(depths[region] - z) <= TRUNK_DEPTH_TOLERANCE * depths[region]
    return np.bincount(region[close & same_depth & np.isfinite(depths[region])], minlength=len(depths))


def reference_trunk_gap_m(trunk: np.ndarray, depth: np.ndarray, geometry: StereoGeometry, pixels: np.ndarray):
    """`trunk_gap_m` as it was: the distance transform over the whole frame."""
    gap_px = cv2.distanceTransform((~trunk).astype(np.uint8), cv2.DIST_L2, 3).ravel()[pixels]
    z = depth.ravel()[pixels]
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(z), gap_px * z / geometry.focal_px, np.inf)


def random_case(seed: int, shape=(180, 320)) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(branch mask, trunk mask, depth m with inf holes, disparity px) of random blobs and strokes: thin lines at
    random depths (some touching the frame's border), a trunk band, speckle and unknown depths."""
    rng = np.random.default_rng(seed)
    height, width = shape
    branch = np.zeros(shape, np.uint8)
    for _ in range(rng.integers(3, 9)):
        a, b = rng.integers(-20, [width + 20, height + 20], size=(2, 2))
        cv2.line(branch, tuple(int(x) for x in a), tuple(int(x) for x in b), 1, int(rng.integers(1, 6)))
    branch = branch.astype(bool) | (rng.random(shape) < 0.01)
    trunk = np.zeros(shape, bool)
    x0 = int(rng.integers(0, width - 40))
    trunk[int(rng.integers(0, 40)) :, x0 : x0 + int(rng.integers(8, 40))] = True
    trunk &= ~branch
    depth = rng.uniform(0.5, 3.0, shape).astype(np.float32)
    depth = cv2.GaussianBlur(depth, (0, 0), 4) + rng.choice([0.0, 0.6], shape, p=[0.9, 0.1]).astype(np.float32)
    depth[rng.random(shape) < 0.05] = np.inf
    disparity = np.where(np.isfinite(depth), GEOMETRY.focal_px * GEOMETRY.baseline_m / depth, 0.0)
    return branch, trunk, depth, disparity.astype(np.float32)


@pytest.fixture(scope="module")
def rendered() -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(branch mask, trunk mask, depth m, disparity px) of two rendered 480×270 scenes."""
    cases = []
    for seed in (0, 1):
        scene = render_scene(seed, SynthCamera.zed_mini(480, 270))
        ids = scene.instance_mask
        depth = np.where(scene.disparity > 0, scene.depth_m, np.inf).astype(np.float32)
        cases.append((is_branch_id(ids), ids == TRUNK_ID, depth, scene.disparity.astype(np.float32)))
    return cases


def all_cases(rendered) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    return [random_case(seed) for seed in range(6)] + rendered


@pytest.mark.parametrize("ratio", [0.0, 0.05, 0.15])
def test_foreground_depth_edges_equal_the_frame_wide_ones_on_the_foreground(rendered, ratio: float) -> None:
    marked = 0
    for branch, _, depth, _ in all_cases(rendered):
        expected = reference_depth_edges(np.where(branch, depth, np.inf), ratio) & branch
        found = foreground_depth_edges(branch, depth, ratio)
        assert np.array_equal(found, expected)
        marked += int(found.sum())
    assert marked > 100  # the cases hold edges to find
    empty = np.zeros((5, 7), bool)
    assert not foreground_depth_edges(empty, np.ones((5, 7), np.float32), 0.1).any()


@pytest.mark.parametrize(("bridge_px", "ratio"), [(0, 0.0), (2, 0.0), (3, 0.2)])
def test_straight_pieces_in_the_masks_box_equal_those_of_the_whole_frame(rendered, bridge_px, ratio) -> None:
    for branch, _, _, disparity in all_cases(rendered):
        ours = list(straight_pieces_of(branch, 20, np.random.default_rng(0), bridge_px, disparity, ratio))
        theirs = list(reference_straight_pieces_of(branch, 20, np.random.default_rng(0), bridge_px, disparity, ratio))
        assert len(ours) == len(theirs) > 0
        for (u, v), (ru, rv) in zip(ours, theirs, strict=True):
            assert np.array_equal(u, ru) and np.array_equal(v, rv)
    assert list(straight_pieces_of(np.zeros((9, 9), bool), 3, np.random.default_rng(0))) == []


def test_the_padded_box_holds_the_mask_and_stays_in_the_frame() -> None:
    mask = np.zeros((10, 12), bool)
    mask[0, 3] = mask[4, 11] = True
    assert padded_box(mask, 2) == (slice(0, 7), slice(1, 12))
    assert padded_box(np.zeros((3, 3), bool), 1) == (slice(0, 0), slice(0, 0))


def test_branch_support_and_trunk_gaps_in_the_box_equal_the_frame_wide_ones(rendered) -> None:
    for branch, trunk, depth, _ in all_cases(rendered):
        count, components = cv2.connectedComponents(trunk.astype(np.uint8), connectivity=8)
        pixels = np.flatnonzero(components)
        region = components.ravel()[pixels]
        depths = np.array([np.inf] + [float(np.median(depth.ravel()[pixels[region == k]])) for k in range(1, count)])
        for max_gap_m in (0.02, 0.1, 1.0):
            arguments = (components, pixels, region, depths, branch, depth, GEOMETRY, max_gap_m)
            assert np.array_equal(_branch_support(*arguments), reference_branch_support(*arguments))
        branch_pixels = np.flatnonzero(branch)
        ours = trunk_gap_m(trunk, depth, GEOMETRY, branch_pixels)
        # OpenCV's float distances of a smaller image may differ in the last bit (measured: 1 float32 ulp)
        np.testing.assert_allclose(ours, reference_trunk_gap_m(trunk, depth, GEOMETRY, branch_pixels), rtol=1e-6)
    branch, _, depth, _ = random_case(0)
    no_trunk = np.zeros(branch.shape, bool)
    pixels = np.flatnonzero(branch)
    np.testing.assert_allclose(
        trunk_gap_m(no_trunk, depth, GEOMETRY, pixels), reference_trunk_gap_m(no_trunk, depth, GEOMETRY, pixels)
    )


def reference_disparity_to_depth(disparity: np.ndarray, geometry: StereoGeometry) -> np.ndarray:
    """`disparity_to_depth` as it was: the valid disparities gathered, divided and scattered back."""
    disparity = np.asarray(disparity, dtype=np.float32)
    depth = np.full(disparity.shape, np.inf, dtype=np.float32)
    valid = valid_disparity(disparity)
    depth[valid] = geometry.focal_px * geometry.baseline_m / disparity[valid]
    return depth


def test_depth_divided_in_place_equals_the_gathered_division(rendered) -> None:
    rng = np.random.default_rng(3)
    noisy = rng.uniform(-5.0, 120.0, (90, 160)).astype(np.float32)
    noisy[rng.random(noisy.shape) < 0.05] = np.nan
    noisy[rng.random(noisy.shape) < 0.05] = np.inf
    for disparity in [noisy, *(case[3] for case in rendered)]:
        assert np.array_equal(
            disparity_to_depth(disparity, GEOMETRY), reference_disparity_to_depth(disparity, GEOMETRY)
        )


@pytest.mark.parametrize("bridge_px", [0, 2, 5])
def test_bridged_regions_of_pixels_in_the_box_equal_the_frame_wide_regions(rendered, bridge_px: int) -> None:
    for branch, _, _, _ in all_cases(rendered):
        pixels = np.flatnonzero(branch)
        count, labels = bridged_regions(branch, bridge_px)  # the frame-wide labelling, as the step had it
        region, region_count = bridged_region_of(branch, bridge_px, pixels)
        pairs = np.unique(np.stack([region, labels.ravel()[pixels]]), axis=1)  # the same regions, any numbering
        assert region_count == count and pairs.shape[1] == len(np.unique(region)) == len(np.unique(pairs[1]))
    assert bridged_region_of(np.zeros((4, 4), bool), 2, np.zeros(0, np.int64))[0].size == 0


def test_straight_pieces_of_a_mask_whose_box_opencv_numbers_otherwise_equal_the_frames() -> None:
    """The learned segmenter's branch mask of held-out scene 50014 (640×360, `benchmarks/segmenter.py`'s first
    seeds): labelled in its box, OpenCV numbered its regions in another order than in the frame, and the pieces
    drawn with the same random lines came out different (114 pixels of that scene's instances)."""
    case = np.load(Path(__file__).parent / "data" / "branch_mask_scene50014.npz")
    mask = np.unpackbits(case["mask"])[: int(np.prod(case["shape"]))].reshape(case["shape"]).astype(bool)
    min_px, bridge_px = int(case["min_px"]), int(case["bridge_px"])
    ours = list(straight_pieces_of(mask, min_px, np.random.default_rng(0), bridge_px))
    theirs = list(reference_straight_pieces_of(mask, min_px, np.random.default_rng(0), bridge_px))
    assert len(ours) == len(theirs) > 0
    for (u, v), (ru, rv) in zip(ours, theirs, strict=True):
        assert np.array_equal(u, ru) and np.array_equal(v, rv)


def reference_straight_pieces(u, v, band_px, min_px, rng, disparity=None, disparity_ratio=0.0, min_gap_px=4.0):
    """`straight_pieces` as it was: each step's (points × lines) tests over all the remaining points at once."""
    points = np.stack([u, v], axis=1).astype(np.float64)
    remaining = np.arange(len(points))
    pieces = []
    while len(remaining) >= min_px and len(pieces) < 6:
        pts = points[remaining]
        pairs = rng.integers(0, len(pts), size=(80, 2))
        d = pts[pairs[:, 1]] - pts[pairs[:, 0]]
        length = np.sqrt(np.add.reduce(d * d, axis=1))
        ok = length > 2.0
        if not ok.any():
            break
        direction = d[ok] / length[ok, None]
        normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
        origin = pts[pairs[ok, 0]]
        remaining_band = band_px[remaining]
        bands = np.maximum(remaining_band[pairs[ok, 0]], remaining_band[pairs[ok, 1]])
        inside = np.abs(pts @ normal.T - np.einsum("kc,kc->k", origin, normal)) < bands
        if disparity is not None and disparity_ratio > 0:
            known = disparity[remaining]
            first, second = known[pairs[ok, 0]], known[pairs[ok, 1]]
            along = (pts @ direction.T - np.einsum("kc,kc->k", origin, direction)) / length[ok]
            expected = first + along * (second - first)
            with np.errstate(invalid="ignore"):
                near = np.abs(known[:, None] - expected) <= np.maximum(
                    PIECE_MIN_DISPARITY_PX, disparity_ratio * np.abs(expected)
                )
            inside &= near | np.isnan(known)[:, None] | np.isnan(expected)
        best = int(np.argmax(inside.sum(axis=0)))
        inliers = np.flatnonzero(inside[:, best])
        gap = max(min_gap_px, 2.0 * float(bands[best]))
        along_best = (pts[inliers] - origin[best]) @ direction[best]
        order = np.argsort(along_best)
        bounds = np.concatenate(([0], np.flatnonzero(np.diff(along_best[order]) > gap) + 1, [len(order)]))
        longest = int(np.argmax(np.diff(bounds)))
        run = order[bounds[longest] : bounds[longest + 1]]
        if len(run) < min_px:
            break
        pieces.append(remaining[inliers[run]])
        unchosen = np.ones(len(remaining), dtype=bool)
        unchosen[inliers[run]] = False
        remaining = remaining[unchosen]
    return pieces


@pytest.mark.parametrize("ratio", [0.0, 0.1])
def test_straight_pieces_tested_in_blocks_of_points_equal_the_whole_arrays_tests(ratio: float) -> None:
    """Crossing noisy strokes of up to ~20 BLOCK_POINTS pixels (a near branch at HD720), each with its own disparity
    ramp (a branch receding), 10 % of the pixels without a disparity: the same pieces, pixel for pixel, as the tests
    over all points at once."""
    for seed in range(40):
        rng = np.random.default_rng(seed)
        count = int(rng.integers(BLOCK_POINTS // 4, 20 * BLOCK_POINTS))
        strokes, ramps = [], []
        for _ in range(int(rng.integers(1, 4))):
            x0, y0, angle = *rng.uniform(0, 600, 2), rng.uniform(0, np.pi)
            along, across = rng.uniform(0, rng.uniform(30, 400), count), rng.uniform(-4, 4, count)
            strokes.append(
                np.round(
                    [
                        x0 + along * np.cos(angle) - across * np.sin(angle),
                        y0 + along * np.sin(angle) + across * np.cos(angle),
                    ]
                )
            )
            ramps.append(rng.uniform(10, 50) + rng.uniform(-0.05, 0.05) * along + rng.normal(0, 0.3, count))
        u, v = np.concatenate(strokes, axis=1).astype(np.int64)
        band = rng.uniform(1.5, 6.0, u.size)
        disparity = np.concatenate(ramps)
        disparity[rng.random(u.size) < 0.1] = np.nan
        ours = straight_pieces(u, v, band, 20, np.random.default_rng(seed), disparity=disparity, disparity_ratio=ratio)
        theirs = reference_straight_pieces(u, v, band, 20, np.random.default_rng(seed), disparity, ratio)
        assert len(ours) == len(theirs) > 0
        assert all(np.array_equal(a, b) for a, b in zip(ours, theirs, strict=True))
