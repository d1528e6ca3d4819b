"""The synthetic scene renderer against its own geometry: exact depth, cut points, photometry, thin twigs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stereo.synth import (
    LEAF_ID,
    TRUNK_ID,
    TWIG_ID,
    SynthCamera,
    SynthOptions,
    is_branch_id,
    render_scene,
)
from stereo.synth.scene import BRANCH_BASE_RADIUS_M, BRANCH_LENGTH_M, build_scene

SEEDS = (0, 1, 2, 3)
CAMERA = SynthCamera.zed_mini(480, 270)


@pytest.fixture(scope="module")
def scenes():
    """Four scenes at 480×270 without sensor noise or view gain differences (exact photometry)."""
    return [render_scene(seed, CAMERA, noise_std=0.0, view_gain_jitter=0.0) for seed in SEEDS]


def back_project(depth: np.ndarray, camera: SynthCamera) -> np.ndarray:
    """3D points `H×W×3` (m, left camera frame) of a depth map."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    z = depth.astype(np.float64)
    return np.stack([(u - camera.cx) * z / camera.focal_px, (v - camera.cy) * z / camera.focal_px, z], axis=-1)


def occluded_in_right(disparity: np.ndarray) -> np.ndarray:
    """Left pixels hidden in the right view: a pixel further right lands on or left of them with a larger disparity."""
    width = disparity.shape[1]
    target = np.arange(width)[None, :] - disparity.astype(np.float64)
    target[disparity <= 0] = np.inf
    later_min = np.minimum.accumulate(target[:, ::-1], axis=1)[:, ::-1]
    shifted = np.concatenate([later_min[:, 1:], np.full((disparity.shape[0], 1), np.inf)], axis=1)
    return shifted < target - 0.5


def test_zed_mini_scales_focal_length_with_width_and_centres_principal_point():
    camera = SynthCamera.zed_mini(640, 360)
    assert camera.focal_px == pytest.approx(320.0)
    assert camera.baseline_m == pytest.approx(0.063)
    assert (camera.cx, camera.cy) == (319.5, 179.5)
    assert SynthCamera.zed_mini(1920, 1080).focal_px == pytest.approx(960.0)
    point = np.array([[0.2, -0.1, 2.0]])
    left, right = camera.project(point, "left")[0], camera.project(point, "right")[0]
    assert left[0] - right[0] == pytest.approx(320.0 * 0.063 / 2.0)
    assert left[1] == pytest.approx(right[1])


def test_camera_rejects_nonpositive_focal_length():
    with pytest.raises(ValueError, match="focal_px"):
        SynthCamera(640, 360, 0.0, 0.063)


def test_options_reject_unknown_keys_and_out_of_range_values():
    with pytest.raises(TypeError, match="cut_ofset"):
        render_scene(0, CAMERA, cut_ofset=0.05)
    with pytest.raises(ValueError, match="cut_offset_m"):
        SynthOptions(cut_offset_m=0.5)
    with pytest.raises(ValueError, match="pose"):
        SynthOptions(pose="sideways")
    with pytest.raises(ValueError, match="leaf_shape"):
        SynthOptions(leaf_shape="pine")


def test_branches_meet_the_specified_geometry():
    for seed in range(12):
        scene = build_scene(np.random.default_rng(seed), CAMERA, SynthOptions())
        assert len(scene.branches) >= 2
        for branch in scene.branches:
            # the ranges are those of the drawn cone; the truth runs from the bark, -1.5 to +12 mm from its start
            assert BRANCH_LENGTH_M[0] - 0.002 <= branch.length_m <= BRANCH_LENGTH_M[1] + 0.012
            assert BRANCH_BASE_RADIUS_M[0] <= branch.base_radius_m <= BRANCH_BASE_RADIUS_M[1] + 0.002
            assert branch.tip_radius_m < branch.base_radius_m
            assert np.linalg.norm(branch.direction) == pytest.approx(1.0)
            axis = np.asarray(branch.base_m) + np.linspace(0, branch.length_m, 20)[:, None] * np.asarray(
                branch.direction
            )
            assert np.all(np.linalg.norm(axis, axis=1) >= 0.3) and np.all(np.linalg.norm(axis, axis=1) <= 4.0)
            assert branch.cut_offset_m == pytest.approx(0.05)
            assert 0 <= branch.cut_pixel[0] < CAMERA.width and 0 <= branch.cut_pixel[1] < CAMERA.height


def test_cut_offset_option_moves_the_cut_point_along_the_axis():
    near = build_scene(np.random.default_rng(5), CAMERA, SynthOptions(cut_offset_m=0.0)).branches[0]
    assert np.allclose(near.cut_point_m, near.base_m)
    far = build_scene(np.random.default_rng(5), CAMERA, SynthOptions(cut_offset_m=0.1)).branches[0]
    assert far.cut_offset_m == pytest.approx(0.1)


def test_depth_of_every_branch_pixel_lies_exactly_on_its_cylinder(scenes):
    for scene in scenes:
        points = back_project(scene.depth_m, scene.camera)
        for branch in scene.branches:
            pts = points[scene.instance_mask == branch.id]
            if len(pts) == 0:
                continue
            rel = pts - np.asarray(branch.base_m)
            s = rel @ np.asarray(branch.direction)
            radial = np.linalg.norm(rel - s[:, None] * np.asarray(branch.direction), axis=1)
            expected = branch.base_radius_m + (branch.tip_radius_m - branch.base_radius_m) * s / branch.length_m
            on_cap = s > branch.length_m - 1e-4
            # float32 depth: relative error ~6e-8 of a few metres
            assert np.all(np.abs(radial - expected)[~on_cap] < 2e-6 * np.maximum(pts[~on_cap, 2], 1.0))
            # the surface continues into the trunk; only a sliver (≈ radius·cot(angle to the trunk)) below
            # the base shows at an oblique junction
            assert np.all((s >= -(4 * branch.base_radius_m + 0.005)) & (s <= branch.length_m + 1e-4))


def test_cut_point_projects_onto_its_branch_with_matching_depth(scenes):
    visible = total = 0
    for scene in scenes:
        for branch in scene.branches:
            x, y = (int(round(c)) for c in branch.cut_pixel)
            cut = np.asarray(branch.cut_point_m)
            depth = float(scene.depth_m[y, x])
            total += 1
            if branch.cut_visible:
                visible += 1
                assert scene.instance_mask[y, x] == branch.id
                ray = np.array(
                    [(x - scene.camera.cx) / scene.camera.focal_px, (y - scene.camera.cy) / scene.camera.focal_px, 1.0]
                )
                sin_angle = np.linalg.norm(np.cross(ray / np.linalg.norm(ray), branch.direction))
                radius = branch.radius_at(branch.cut_offset_m)
                slack = 1.5 * radius / max(sin_angle, 0.2) + 3 * cut[2] / scene.camera.focal_px
                assert abs(depth - cut[2]) <= slack, (branch.id, depth, cut[2], slack)
            else:
                # never a farther surface at the cut point, unless the branch is thinner than a pixel there
                width_px = 2 * branch.radius_at(branch.cut_offset_m) * scene.camera.focal_px / cut[2]
                assert depth < cut[2] or width_px < 1.5, (branch.id, depth, cut[2], width_px)
    assert visible >= 0.6 * total, f"only {visible} of {total} cut points visible"


def depth_edges(depth: np.ndarray) -> np.ndarray:
    """Pixels within one pixel of a depth discontinuity (> 2 % log-depth Laplacian), where pixels mix surfaces."""
    log_depth = np.log(np.where(np.isfinite(depth), depth, 1e4).astype(np.float64))
    jumps = (np.abs(cv2.Laplacian(log_depth, cv2.CV_64F)) > 0.02).astype(np.uint8)
    return cv2.dilate(jumps, np.ones((3, 3), np.uint8)) > 0


def warp_errors(scene) -> tuple[float, float, float]:
    """Mean |left − right warped by the truth disparity| (grey levels) on non-occluded pixels, the same away
    from depth edges, and |left − right| with zero disparity on those pixels."""
    height, width = scene.disparity.shape
    valid = (scene.disparity > 0) & ~occluded_in_right(scene.disparity)
    xs = np.arange(width, dtype=np.float32)[None, :] - scene.disparity
    valid &= xs >= 0
    ys = np.repeat(np.arange(height, dtype=np.float32)[:, None], width, axis=1)
    warped = cv2.remap(scene.right, xs.astype(np.float32), ys, cv2.INTER_LINEAR).astype(np.float64)
    left, right = scene.left.astype(np.float64), scene.right.astype(np.float64)
    error = np.abs(warped - left).mean(axis=2)
    zero = np.abs(right - left).mean(axis=2)
    return error[valid].mean(), error[valid & ~depth_edges(scene.depth_m)].mean(), zero[valid].mean()


def test_warping_right_into_left_with_truth_disparity_matches_and_zero_disparity_does_not(scenes):
    truth, smooth, zero = zip(*(warp_errors(scene) for scene in scenes))
    # measured (grey levels): 3.0 on all non-occluded pixels, 0.7 away from depth edges, 13.9 with zero disparity
    assert np.mean(smooth) < 1.5, smooth
    assert np.mean(truth) < 4.5, truth
    assert np.mean(zero) > 3 * np.mean(truth), (truth, zero)


def test_any_focal_length_and_baseline_give_a_consistent_pair():
    camera = SynthCamera(320, 180, 250.0, 0.12)
    scene = render_scene(2, camera, noise_std=0.0, view_gain_jitter=0.0)
    finite = np.isfinite(scene.depth_m)
    assert np.allclose(scene.disparity[finite], 250.0 * 0.12 / scene.depth_m[finite], rtol=1e-5)
    truth, smooth, zero = warp_errors(scene)
    # measured 5.2 (depth edges included), 0.9 and 32.6 grey levels
    assert smooth < 2.0 and truth < 7.0 and zero > 3 * truth, (truth, smooth, zero)


def test_sensor_noise_and_view_gain_jitter_are_applied_per_view():
    camera = SynthCamera.zed_mini(160, 96)
    clean = render_scene(4, camera, noise_std=0.0, view_gain_jitter=0.0)
    noisy = render_scene(4, camera, noise_std=4.0, view_gain_jitter=0.0)
    noise = [noisy.left.astype(np.float64) - clean.left, noisy.right.astype(np.float64) - clean.right]
    unclipped = [(c > 12) & (c < 243) for c in (clean.left, clean.right)]
    for n, keep in zip(noise, unclipped):
        assert 3.6 < n[keep].std() < 4.4
    both = unclipped[0] & unclipped[1]
    assert abs(np.corrcoef(noise[0][both], noise[1][both])[0, 1]) < 0.05  # drawn independently per view
    jittered = render_scene(4, camera, noise_std=0.0, view_gain_jitter=0.2)
    # per-channel gain of each view (±10 % at most); measured left (1.00, 0.98, 1.06), right (0.99, 1.07, 0.96)
    gains = np.array(
        [
            [(j[..., ch][k[..., ch]] / c[..., ch][k[..., ch]].astype(np.float64)).mean() for ch in range(3)]
            for j, c, k in ((jittered.left, clean.left, unclipped[0]), (jittered.right, clean.right, unclipped[1]))
        ]
    )
    assert np.all(np.abs(gains - 1.0) < 0.11) and np.abs(gains[0] - gains[1]).max() > 0.02, gains
    assert np.array_equal(jittered.instance_mask, clean.instance_mask)


def test_every_scene_has_branch_pixels_under_4_px_wide(scenes):
    kernel = np.ones((4, 4), np.uint8)
    for scene in scenes:
        branch = is_branch_id(scene.instance_mask).astype(np.uint8)
        thin = (branch > 0) & (cv2.morphologyEx(branch, cv2.MORPH_OPEN, kernel) == 0)
        assert thin.sum() >= 20, f"scene {scene.seed}: {thin.sum()} thin branch pixels"


def test_thin_twigs_are_antialiased_not_aliased():
    sharp = render_scene(9, CAMERA, supersample=1, noise_std=0.0, view_gain_jitter=0.0)
    smooth = render_scene(9, CAMERA, supersample=3, noise_std=0.0, view_gain_jitter=0.0)
    twig = smooth.instance_mask == TWIG_ID
    assert twig.sum() > 50
    # same geometry and truth; the supersampled image blends twig and background colours
    assert np.array_equal(sharp.instance_mask, smooth.instance_mask)
    grey_sharp, grey_smooth = (s.left.astype(np.float64).mean(axis=2) for s in (sharp, smooth))
    edge_energy = [np.abs(np.diff(g, axis=1))[twig[:, 1:]].mean() for g in (grey_sharp, grey_smooth)]
    assert edge_energy[1] < edge_energy[0]


def test_needle_clusters_are_thin_leaf_pixels_on_the_same_branches():
    broad, needles = (
        render_scene(1, CAMERA, foliage="dense", leaf_shape=shape, noise_std=0.0, view_gain_jitter=0.0)
        for shape in ("broad", "needles")
    )
    assert (broad.leaf_shape, needles.leaf_shape) == ("broad", "needles")
    kept = []
    for scene in (broad, needles):
        leaf = (scene.instance_mask == LEAF_ID).astype(np.uint8)
        assert leaf.sum() > 500
        kept.append(cv2.morphologyEx(leaf, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)).sum() / leaf.sum())
    # a 3×3 opening keeps most of the blades' pixels and few of the needles' (measured 0.88 and 0.09)
    assert kept[0] > 0.7 and kept[1] < 0.3, kept
    geometry = [
        [(b.id, b.base_m, b.direction, b.length_m, b.base_radius_m) for b in s.branches] for s in (broad, needles)
    ]
    assert geometry[0] == geometry[1]


def test_auto_leaf_shape_draws_both_kinds_over_seeds():
    shapes = {
        build_scene(np.random.default_rng(seed), CAMERA, SynthOptions(leaf_shape="auto")).leaf_shape
        for seed in range(5)
    }
    assert shapes == {"broad", "needles"}


def test_scene_uses_reserved_ids_and_inf_depth_only_on_sky(scenes):
    ids = np.concatenate([np.unique(s.instance_mask) for s in scenes])
    assert TRUNK_ID in ids and TWIG_ID in ids and 0 in ids
    for scene in scenes:
        sky = ~np.isfinite(scene.depth_m)
        assert np.all(scene.disparity[sky] == 0)
        assert np.all(scene.instance_mask[sky] == 0)
        finite = np.isfinite(scene.depth_m)
        assert np.allclose(
            scene.disparity[finite], scene.camera.focal_px * scene.camera.baseline_m / scene.depth_m[finite], rtol=1e-5
        )
        assert scene.left.dtype == np.uint8 and scene.left.shape == (270, 480, 3)
    assert any(LEAF_ID in np.unique(s.instance_mask) for s in scenes) or all(s.foliage == "bare" for s in scenes)


def test_same_seed_gives_identical_scene_and_different_seed_does_not():
    camera = SynthCamera.zed_mini(160, 96)
    a, b, c = render_scene(11, camera, threads=2), render_scene(11, camera, threads=1), render_scene(12, camera)
    for name in ("left", "right", "disparity", "instance_mask"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert a.branches == b.branches
    assert not np.array_equal(a.left, c.left)


@pytest.mark.parametrize("pose", ["upward", "parallel", "downward"])
def test_pose_classes_point_the_camera_as_named(pose):
    scene = build_scene(np.random.default_rng(3), CAMERA, SynthOptions(pose=pose))
    # world "up" seen in the camera frame: its z component is positive when the camera looks up
    up_in_camera = scene.sky.world_from_camera.T @ np.array([0.0, -1.0, 0.0])
    expected = {
        "upward": up_in_camera[2] > 0.2,
        "parallel": abs(up_in_camera[2]) < 0.2,
        "downward": up_in_camera[2] < -0.2,
    }
    assert expected[pose], up_in_camera
