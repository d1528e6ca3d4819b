"""The branches' own disparity refinement: analytic pairs with a known sub-pixel disparity, a rendered
scene through the pipeline, and the cases where it must leave a branch alone."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from branchrange.core.branch_disparity import refine_branch_disparity
from branchrange.core.frame_result import FrameResult
from branchrange.core.masks import DEFAULT_TRUNK_ID, BranchMasks
from branchrange.core.pipeline import Pipeline, PipelineInputError, untracked_whole_frame
from stereo.backends import make_backend
from stereo.synth import SynthCamera, render_scene

HEIGHT, WIDTH = 120, 200
SUPERSAMPLE = 8
BACKGROUND_DISPARITY = 6.0


def _background(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth, textured backdrop (grey levels) at continuous left-image coordinates."""
    return 110 + 30 * np.sin(0.37 * x + 0.9) * np.cos(0.21 * y) + 25 * np.sin(0.11 * x - 0.23 * y + 2.0)


def _render_pair(stem: dict, disparity: float) -> tuple[np.ndarray, np.ndarray]:
    """Left and right `uint8 H×W` grey images of a stem before the backdrop, box-filtered from
    `SUPERSAMPLE`² samples per pixel, so the stem's edges are the mixed pixels a camera sees.
    `stem`: ("vertical", x0, width, y0, y1) spans columns [x0, x0 + width) in the left image, and
    ("horizontal", y0, width, x0, x1) rows [y0, y0 + width); the right view sees the stem `disparity`
    px to the left and the backdrop `BACKGROUND_DISPARITY` px to the left."""
    offsets = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    images = []
    for shift in (0.0, 1.0):  # left, right
        total = np.zeros((HEIGHT, WIDTH))
        for dy in offsets:
            for dx in offsets:
                x, y = u + dx, v + dy
                xs = x + shift * disparity  # the stem's own left-image coordinate
                if stem["kind"] == "vertical":
                    on = (xs >= stem["x0"]) & (xs < stem["x0"] + stem["width"]) & (y >= stem["y0"]) & (y < stem["y1"])
                    texture = 70 + 25 * np.sin(0.8 * y)
                else:
                    on = (y >= stem["y0"]) & (y < stem["y0"] + stem["width"]) & (xs >= stem["x0"]) & (xs < stem["x1"])
                    texture = np.full_like(x, 70.0)  # no texture along the rows: nothing to match
                total += np.where(on, texture, _background(x + shift * BACKGROUND_DISPARITY, y))
        images.append(np.clip(total / SUPERSAMPLE**2, 0, 255).astype(np.uint8))
    return images[0], images[1]


def _stem_mask(stem: dict) -> np.ndarray:
    """Instance labels `H×W`: the stem's pixels (those mostly covered in the left image) carry id 1."""
    labels = np.zeros((HEIGHT, WIDTH), dtype=np.int32)
    if stem["kind"] == "vertical":
        labels[stem["y0"] : stem["y1"], stem["x0"] : stem["x0"] + stem["width"]] = 1
    else:
        labels[stem["y0"] : stem["y0"] + stem["width"], stem["x0"] : stem["x1"]] = 1
    return labels


VERTICAL = {"kind": "vertical", "x0": 120, "width": 3, "y0": 15, "y1": 105}
HORIZONTAL = {"kind": "horizontal", "y0": 60, "width": 3, "x0": 40, "x1": 160}


@pytest.mark.parametrize("bias", [-0.8, -0.3, 0.5, 2.2])
def test_a_thin_stem_gets_its_own_subpixel_disparity(bias: float) -> None:
    """A 3 px stem at 20.3 px before a backdrop at 6 px, given a disparity `bias` px off and scattered by
    ±0.3 px (as a block matcher pulled by the backdrop gives it), gets the refined line: every pixel
    within 0.1 px of the truth."""
    truth = 20.3
    left, right = _render_pair(VERTICAL, truth)
    labels = _stem_mask(VERTICAL)
    scatter = np.random.default_rng(5).uniform(-0.3, 0.3, labels.shape)
    disparity = np.where(labels == 1, truth + bias + scatter, BACKGROUND_DISPARITY).astype(np.float32)
    rows, cols = np.nonzero(labels == 1)
    outliers = np.zeros(labels.shape, dtype=bool)
    outliers[rows[3::11], cols[3::11]] = True
    disparity[outliers] += 1.5  # mismatches, beyond the line's agreement
    disparity[rows[::7], cols[::7]] = 0.0  # holes stay holes
    masks = BranchMasks(labels, None, "test")
    confidence = np.ones_like(disparity)
    out = refine_branch_disparity(left, right, disparity, masks, confidence)
    refined, shifts = out.disparity, out.shifts
    stem = labels == 1
    assert len(shifts) == 1 and shifts[0].mask_id == 1
    assert shifts[0].cost_after < shifts[0].cost_before
    assert np.abs(refined[stem & (disparity > 0)] - truth).max() < 0.1  # the line, not the scatter shifted
    assert np.array_equal(refined[~stem], disparity[~stem])  # the backdrop is not a branch: untouched
    assert np.array_equal(refined == 0, disparity == 0)
    # the scatter the line replaced still lowers the confidence: ±0.3 px → 0.85..1, mismatches → 0; not the bias
    agreeing = stem & ~outliers & (disparity > 0)  # `confidence` is scaled in place
    assert (confidence[agreeing] >= 0.8).all()
    assert float(np.mean(confidence[agreeing])) == pytest.approx(0.925, abs=0.03)
    assert (confidence[outliers & (disparity > 0)] == 0).all()
    assert (confidence[~stem] == 1).all()  # elsewhere untouched


def test_holes_in_a_branch_stay_holes() -> None:
    """Where the block matcher's own line is refined, pixels without a valid disparity are not given one:
    the cut point's evidence is unchanged in kind."""
    left, right = _render_pair(VERTICAL, 20.3)
    labels = _stem_mask(VERTICAL)
    disparity = np.where(labels == 1, 19.8, BACKGROUND_DISPARITY).astype(np.float32)
    disparity[VERTICAL["y0"] : VERTICAL["y0"] + 30, :] = 0.0
    out = refine_branch_disparity(left, right, disparity, BranchMasks(labels, None, "test"))
    refined, shifts = out.disparity, out.shifts
    assert len(shifts) == 1
    assert np.array_equal(refined == 0, disparity == 0)


def test_a_stem_along_the_rows_is_left_alone() -> None:
    """No texture across the rows (the aperture problem): nothing to match, so its disparity stays what
    the block matcher said, not drifting to the backdrop's or to any other shift."""
    left, right = _render_pair(HORIZONTAL, 20.3)
    labels = _stem_mask(HORIZONTAL)
    disparity = np.where(labels == 1, 19.5, BACKGROUND_DISPARITY).astype(np.float32)
    out = refine_branch_disparity(left, right, disparity, BranchMasks(labels, None, "test"))
    assert out.shifts == []
    assert np.array_equal(out.disparity, disparity)


@pytest.mark.parametrize(
    "given",
    [0.0, BACKGROUND_DISPARITY, 20.3 + 9.0],
    ids=["all holes", "the backdrop's disparity", "9 px too near"],
)
def test_a_stem_the_matcher_missed_is_found_over_the_whole_range(given: float) -> None:
    """A block matcher whose window saw the backdrop gives a thin stem holes or the backdrop's disparity,
    beyond any search around its own values. The whole-range search finds the stem's match: every stem
    pixel, holes included, takes the line within 0.1 px of the truth, with a confidence from how distinct
    the match is (one stem, no rival: full)."""
    truth = 20.3
    left, right = _render_pair(VERTICAL, truth)
    labels = _stem_mask(VERTICAL)
    stem = labels == 1
    disparity = np.where(stem, given, BACKGROUND_DISPARITY).astype(np.float32)
    given_confidence = np.where(disparity > 0, 0.9, 0.0).astype(np.float32)
    confidence = given_confidence.copy()
    out = refine_branch_disparity(left, right, disparity, BranchMasks(labels, None, "test"), confidence)
    assert len(out.shifts) == 1 and out.shifts[0].searched
    assert np.abs(out.disparity[stem] - truth).max() < 0.1
    assert np.array_equal(out.disparity[~stem], disparity[~stem])
    assert (confidence[stem] == 1.0).all()
    assert np.array_equal(confidence[~stem], given_confidence[~stem])


def test_an_ambiguous_match_is_found_with_no_confidence() -> None:
    """The right view shows the stem twice (an exact twin, backdrop and all, 20 px farther along the row):
    both shifts match it equally well, so the searched line, whichever it is, carries no confidence."""
    left, right = _render_pair(VERTICAL, 20.3)
    band = slice(VERTICAL["x0"] - 26, VERTICAL["x0"] - 11)  # the right view's stem (at 99.7–102.7) ± 5 px
    right[:, band.start - 20 : band.stop - 20] = right[:, band]
    labels = _stem_mask(VERTICAL)
    stem = labels == 1
    disparity = np.where(stem, 0.0, BACKGROUND_DISPARITY).astype(np.float32)
    confidence = np.where(disparity > 0, 0.9, 0.0).astype(np.float32)
    out = refine_branch_disparity(left, right, disparity, BranchMasks(labels, None, "test"), confidence)
    assert len(out.shifts) == 1 and out.shifts[0].searched
    found = float(np.median(out.disparity[stem]))
    assert min(abs(found - 20.3), abs(found - 40.3)) < 0.2
    assert confidence[stem].max() < 0.1


def test_the_disparity_offset_is_taken_out_before_matching() -> None:
    """With Middlebury's `doffs` folded into the disparity, the views still differ by `d − doffs`."""
    truth, doffs = 20.3, 55.0
    left, right = _render_pair(VERTICAL, truth)
    labels = _stem_mask(VERTICAL)
    disparity = np.where(labels == 1, truth - 0.6 + doffs, BACKGROUND_DISPARITY + doffs).astype(np.float32)
    refined = refine_branch_disparity(
        left, right, disparity, BranchMasks(labels, None, "test"), doffs_px=doffs
    ).disparity
    assert abs(float(np.median(refined[labels == 1])) - (truth + doffs)) < 0.1


@pytest.fixture(scope="module")
def rendered_scene() -> dict:
    """A 640×360 synthetic scene with its SGBM disparity and truth masks."""
    scene = render_scene(50004, SynthCamera.zed_mini(640, 360))
    stereo = make_backend("sgbm", max_disp=192).compute(scene.left, scene.right)
    ids = scene.instance_mask.astype(np.int32)
    branch_ids = np.where((ids > 0) & (ids < 65533), ids, 0)
    labels = np.where(branch_ids > 0, branch_ids, np.where(ids == 65535, DEFAULT_TRUNK_ID, 0))
    return {"scene": scene, "sgbm": stereo, "labels": labels, "branches": branch_ids > 0}


def _run_pipeline(rendered: dict, refine: bool, right: np.ndarray | None) -> tuple[FrameResult, np.ndarray]:
    """The rendered scene's SGBM disparity and true masks through the pipeline (`refine_branches` as
    given, the right image or None): its result and the disparity its cut points were fitted on."""
    scene, sgbm = rendered["scene"], rendered["sgbm"]
    config = untracked_whole_frame()
    config = replace(config, stereo=replace(config.stereo, refine_branches=refine))
    pipeline = Pipeline(config, focal_px=scene.camera.focal_px, baseline_m=scene.camera.baseline_m)
    result = pipeline.process_disparity(
        scene.left, sgbm.disparity, sgbm.confidence, mask=rendered["labels"], right=right
    )
    assert pipeline.last is not None
    return result, pipeline.last.disparity


def _cut_point_errors(rendered: dict, refine: bool) -> np.ndarray:
    """Distances (m) from each visible true cut point to the pipeline's cut point of the same branch."""
    scene = rendered["scene"]
    result, _ = _run_pipeline(rendered, refine, scene.right)
    truth = {index + 1: branch for index, branch in enumerate(scene.branches)}
    return np.array(
        [
            np.linalg.norm(np.asarray(b.cut_point_m) - truth[b.mask_id].cut_point_m)
            for b in result.branches
            if truth[b.mask_id].cut_visible
        ]
    )


def test_refinement_brings_the_cut_points_of_rendered_branches_nearer(rendered_scene: dict) -> None:
    """With SGBM and the true masks, the refined disparity puts the scene's cut points nearer the true
    ones (the segmenter benchmark measures this over many scenes; here one whose stems are thin)."""
    plain, refined = _cut_point_errors(rendered_scene, False), _cut_point_errors(rendered_scene, True)
    assert len(refined) == len(plain) >= 4
    assert np.median(refined) < 0.75 * np.median(plain)
    assert np.mean(refined <= 0.05) >= np.mean(plain <= 0.05)


def test_refinement_leaves_the_trunk_and_the_backdrop_alone(rendered_scene: dict) -> None:
    scene, sgbm = rendered_scene["scene"], rendered_scene["sgbm"]
    masks = BranchMasks(rendered_scene["labels"], DEFAULT_TRUNK_ID, "truth")
    disparity = np.where(np.isfinite(sgbm.disparity), sgbm.disparity, 0).astype(np.float32)
    out = refine_branch_disparity(scene.left, scene.right, disparity, masks, max_disparity=192)
    refined, shifts = out.disparity, out.shifts
    assert len(shifts) >= 3
    not_branch = ~rendered_scene["branches"]
    assert np.array_equal(refined[not_branch], disparity[not_branch])


def test_the_pipeline_refines_only_with_a_right_image_and_the_setting_on(rendered_scene: dict) -> None:
    right = rendered_scene["scene"].right
    refined, refined_disparity = _run_pipeline(rendered_scene, True, right)
    plain, plain_disparity = _run_pipeline(rendered_scene, False, right)
    without_right, without_right_disparity = _run_pipeline(rendered_scene, True, None)
    assert "branch_disparity" in refined.timing_ms and "branch_disparity" not in plain.timing_ms
    assert np.array_equal(plain_disparity, without_right_disparity)
    assert not np.array_equal(refined_disparity, plain_disparity)
    assert len(plain.branches) == len(without_right.branches)
    for a, b in zip(plain.branches, without_right.branches):
        assert a.cut_point_m == b.cut_point_m


def test_a_right_image_of_another_size_is_refused(rendered_scene: dict) -> None:
    scene = rendered_scene["scene"]
    pipeline = Pipeline(untracked_whole_frame(), focal_px=scene.camera.focal_px, baseline_m=scene.camera.baseline_m)
    with pytest.raises(PipelineInputError, match="right image is 320×360"):
        pipeline.process_disparity(scene.left, scene.disparity, right=scene.right[:, :320])
