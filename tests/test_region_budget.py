"""The roi mode's region budget (`branchrange.core.region_budget`, issue 37 item 4).

The rule on its own (a near branch shrunk, a far or thin one not, the frame's caps always held), then on a
rendered HD720 frame 0.8 m from the approached cut point (`stereo.synth.flight`, truth masks): the near
regions are matched at a reduced scale, each such cut point within 5 mm of the full-resolution one (both
within 1 cm of the truth: at 0.8 m the regions are 4–16× the pixels a cut point needs; measured 1.5 → 1.2 mm
and 1.6 → 3.0 mm), and its result says so; its covariance in the MAVLink relay grows with the scale.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from branchrange.config.sections import TrackingConfig
from branchrange.core.cutpoints import CutPointConfig
from branchrange.core.masks import BranchMasks
from branchrange.core.pipeline import Pipeline, PipelineConfig, StereoConfig
from branchrange.core.region_budget import (
    RegionNeed,
    branch_scales,
    fit_budget,
    match_region,
    on_working_grid,
    region_cost,
    working_scale,
)
from branchrange.core.roi import Region, RoiConfig
from stereo.backends import make_backend

ON = RoiConfig()


def test_a_near_wide_branch_is_shrunk_a_far_or_thin_one_is_not():
    # HD720, ZED Mini (f·B ≈ 40 px·m): 0.8 m → d ≈ 50 px; 3 m → 13 px
    assert working_scale(RegionNeed(disparity_px=50.0, width_px=12.0), ON) == 2
    assert working_scale(RegionNeed(disparity_px=70.0, width_px=20.0), ON) == 4
    assert working_scale(RegionNeed(disparity_px=13.0, width_px=12.0), ON) == 1  # far: the disparity rule
    assert working_scale(RegionNeed(disparity_px=70.0, width_px=6.0), ON) == 1  # a thin stem: the width rule
    assert working_scale(RegionNeed(disparity_px=0.0, width_px=0.0), ON) == 1  # no coarse evidence
    assert working_scale(RegionNeed(disparity_px=500.0, width_px=500.0), ON) == ON.budget_max_scale
    assert working_scale(RegionNeed(disparity_px=70.0, width_px=20.0), replace(ON, budget=False)) == 1


def _totals(regions: list[Region]) -> tuple[int, int]:
    costs = [region_cost(r.box, r.d_min, r.d_range, r.scale) for r in regions]
    return sum(c[0] for c in costs), sum(c[1] for c in costs)


def test_the_frames_caps_hold_by_shrinking_the_nearest_first_then_leaving_out_the_farthest():
    # eight 300×300 regions, disparities 10..80 px, all wide: 720 kpx at full resolution
    regions = [Region(i + 1, (0, 0, 300, 300), 0, 96) for i in range(8)]
    needs = [RegionNeed(10.0 * (i + 1), 40.0) for i in range(8)]
    config = replace(ON, budget_max_pixels=250_000, budget_max_cost_mpd=8.0)
    fitted = fit_budget(regions, needs, config)
    pixels, cost = _totals(fitted)
    assert pixels <= config.budget_max_pixels and cost <= config.budget_max_cost_mpd * 1e6
    assert len(fitted) == 8  # shrinking was enough
    by_id = {r.instance_id: r.scale for r in fitted}
    assert by_id[8] >= by_id[1]  # the nearest gave up resolution first
    # without the rule's reductions (every branch thin: width 4 px at full resolution) the farthest are left out
    thin = [RegionNeed(10.0 * (i + 1), 4.0) for i in range(8)]
    roomy = replace(config, budget_max_cost_mpd=30.0)  # 3 × 8.6 M pixel-disparities fit, 3 × 90 kpx do not
    kept = fit_budget(regions, thin, roomy)
    assert _totals(kept)[0] <= config.budget_max_pixels and all(r.scale == 1 for r in kept)
    assert [r.instance_id for r in kept] == [7, 8]  # 2 × 90 kpx ≤ 250 kpx < 3 × 90 kpx: the nearest kept
    assert [r.scale for r in fit_budget(regions, needs, replace(config, budget=False))] == [1] * 8


def test_a_region_matched_at_half_scale_gives_full_resolution_disparities_on_the_working_grid():
    rng = np.random.default_rng(3)
    texture = rng.integers(0, 255, (240, 400), dtype=np.uint8)
    texture = np.repeat(np.repeat(texture[:120, :200], 2, axis=0), 2, axis=1)  # smooth enough at half scale
    shift = 40  # a fronto-parallel plane 40 px of disparity away
    left = np.stack([texture] * 3, axis=-1)
    right = np.roll(left, -shift, axis=1)
    backend = make_backend("sgbm", max_disp=128)
    region = Region(1, (150, 60, 330, 190), 16, 48, scale=2)
    disparity, confidence = match_region(backend, left, right, region)
    assert disparity.shape == confidence.shape == (130, 180)
    valid = disparity > 0
    assert valid.mean() > 0.8
    assert np.median(np.abs(disparity[valid] - shift)) <= 1.0  # ± half a working pixel × 2
    # one value per 2×2 block aligned to even full-resolution pixels
    assert np.all(disparity[0::2, 0::2] == disparity[1::2, 1::2])
    rows, cols = np.nonzero(np.ones((4, 4), bool))
    assert on_working_grid(rows, cols, 2).sum() == 4 and on_working_grid(rows, cols, 1).all()
    # a piece with too few pixels on the grid (an odd row) keeps all of them: they are all its evidence
    odd, even = (np.full(6, 3), np.arange(6)), (np.full(6, 2), np.arange(6))
    assert on_working_grid(*odd, 2).all()
    assert on_working_grid(*even, 2, minimum=3).tolist() == [True, False] * 3
    assert on_working_grid(*even, 2, minimum=4).all()


def test_a_branch_takes_the_scale_most_of_its_pixels_were_matched_at():
    labels = np.zeros((20, 20), np.int32)
    labels[2:6, 2:18] = 1
    labels[10:14, 2:18] = 2
    working = np.ones((20, 20), np.uint8)
    working[:, :12] = 2  # branch 1 and 2: 10 of 16 columns at scale 2
    working[10:14, :] = 1
    scales = branch_scales(BranchMasks(labels), working)
    assert scales == {1: 2}
    assert branch_scales(BranchMasks(labels), None) == {}


@pytest.fixture(scope="module")
def close_frame():
    """An HD720 frame 0.8 m from the approached cut point (seed 1), rendered once."""
    from stereo.synth.flight import FlightRenderer
    from stereo.synth.flight_path import FlightOptions

    renderer = FlightRenderer(FlightOptions(frames=2, width=1280, height=720, start_m=0.85, end_m=0.8, seed=1))
    return renderer.camera, renderer.render(1)


def _process(close_frame, budget: bool):
    camera, frame = close_frame
    pipeline = Pipeline(
        PipelineConfig(
            stereo=StereoConfig(mode="roi", max_disp=128),
            roi=replace(ON, budget=budget),
            cutpoints=CutPointConfig(tracking=False),
        ),
        focal_px=camera.focal_px,
        baseline_m=camera.baseline_m,
        principal_point=(camera.cx, camera.cy),
    )
    return pipeline.process(frame.left, frame.right, mask=frame.mask)


def test_near_cut_points_at_reduced_scale_stay_within_5_mm_of_full_resolution_ones(close_frame):
    _, frame = close_frame
    truth = {b.id: np.asarray(b.cut_point_m) for b in frame.branches}
    full, budgeted = _process(close_frame, budget=False), _process(close_frame, budget=True)
    assert all(r.scale is None for r in full.roi.regions)
    reduced = {r.id for r in budgeted.roi.regions if r.scale}
    assert reduced, "at 0.8 m the near regions are matched at a reduced scale"
    full_cuts = {b.mask_id: b for b in full.branches}
    compared = 0
    for branch in budgeted.branches:
        if branch.mask_id not in reduced or branch.mask_id not in full_cuts:
            continue
        compared += 1
        assert branch.disparity_scale is not None and branch.disparity_scale >= 2
        reference = full_cuts[branch.mask_id]
        assert reference.disparity_scale is None
        assert np.linalg.norm(np.subtract(branch.cut_point_m, reference.cut_point_m)) <= 0.005
        assert np.linalg.norm(np.subtract(branch.cut_point_m, truth[branch.mask_id])) <= 0.01
        assert branch.points < reference.points  # one point per working pixel
    assert compared >= 1
    pixels = sum((r.box[2] - r.box[0]) * (r.box[3] - r.box[1]) // (r.scale or 1) ** 2 for r in budgeted.roi.regions)
    assert pixels < sum((r.box[2] - r.box[0]) * (r.box[3] - r.box[1]) for r in full.roi.regions)


@pytest.mark.parametrize("exponent", [0.5, 1.0])
def test_the_relay_fuses_a_reduced_scale_cut_point_with_a_sigma_grown_by_the_scale_exponent(exponent: float):
    """Two branches at the same range in one result, one matched at scale 2: its track's σ is 2^α times the
    other's (α = `tracking.scale_exponent`: 0.5 as measured, 1 if an error were whole px of the shrunk image)."""
    import time

    from autopilot_sim import AutopilotSim, approach_flight
    from result_factory import branch, frame_result

    from branchrange.config.sections import MavlinkConfig
    from branchrange.onboard.mavlink import CameraMount, MavlinkRelay

    mount = CameraMount.from_rpy((0.0, -10.0, 0.0), (0.12, 0.0, 0.04))
    full = branch(1, (-0.2, 0.0, 0.8), confidence=0.8)
    scaled = replace(branch(2, (0.2, 0.0, 0.8), confidence=0.8), disparity_scale=2)
    with AutopilotSim(approach_flight(0.0), heartbeat_period_s=0.2) as sim:
        cfg = MavlinkConfig(url=f"udpout:127.0.0.1:{sim.port}", send_rate_hz=10.0, state_rate_hz=50.0)
        with MavlinkRelay(cfg, mount, tracking=TrackingConfig(scale_exponent=exponent)) as relay:
            deadline = time.monotonic() + 3.0
            while not relay.link_state()["vehicle_state"]["available"]:
                assert time.monotonic() < deadline, relay.link_state()
                time.sleep(0.02)
            captured = time.monotonic()
            relay.publish(frame_result([full, scaled], focal_px=640.0, baseline_m=0.063), captured_at=captured)
            tracks = {t.branch_id: t for t in relay.targets().tracks}
    assert set(tracks) == {1, 2}
    assert tracks[2].sigma_m == pytest.approx(2.0**exponent * tracks[1].sigma_m, rel=0.02)


def test_the_pipeline_holds_a_tight_frame_budget_on_the_close_frame(close_frame):
    """Caps far below what the close frame's regions need: the regions matched fit them (shrunk, then the
    farthest left out), and what is kept is still matched and gives cut points."""
    camera, frame = close_frame
    tight = replace(ON, budget_max_pixels=20_000, budget_max_cost_mpd=0.5)
    pipeline = Pipeline(
        PipelineConfig(
            stereo=StereoConfig(mode="roi", max_disp=128), roi=tight, cutpoints=CutPointConfig(tracking=False)
        ),
        focal_px=camera.focal_px,
        baseline_m=camera.baseline_m,
        principal_point=(camera.cx, camera.cy),
    )
    result = pipeline.process(frame.left, frame.right, mask=frame.mask)
    kept = [Region(r.id, r.box, r.d_min, r.d_range, scale=r.scale or 1) for r in result.roi.regions]
    pixels, cost = _totals(kept)
    assert kept and pixels <= tight.budget_max_pixels and cost <= tight.budget_max_cost_mpd * 1e6
    assert len(kept) < len(_process(close_frame, budget=False).roi.regions)  # something had to give
    assert result.branches


def test_the_trunk_near_the_tree_is_fitted_on_a_capped_number_of_points_with_the_same_axis(close_frame):
    camera, frame = close_frame
    pipeline = Pipeline(
        PipelineConfig(stereo=StereoConfig(mode="roi", max_disp=128), roi=ON, cutpoints=CutPointConfig(tracking=False)),
        focal_px=camera.focal_px,
        baseline_m=camera.baseline_m,
        principal_point=(camera.cx, camera.cy),
    )
    trunk = pipeline.stereo_stage(frame.left, frame.right, frame.mask).coarse_trunk
    assert trunk is not None and trunk.crop.mask.sum() > 4 * 2000
    every, capped = trunk.fit(pipeline.config.cutpoints), trunk.fit(pipeline.config.cutpoints, max_points=2000)
    assert every is not None and capped is not None
    assert capped.cylinder.points.shape[0] <= 2000 < every.cylinder.points.shape[0]
    cosine = abs(float(capped.cylinder.axis.direction @ every.cylinder.axis.direction))
    assert cosine > np.cos(np.radians(2.0))
    point = every.cylinder.axis.point
    assert every.surface_distance(point) == pytest.approx(capped.surface_distance(point), abs=0.01)
