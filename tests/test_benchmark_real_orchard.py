"""`benchmarks/segmenter.py --real-orchard` (`benchmarks/real_orchard.py`) on a tiny stand-in data set.

Why: the real orchard figures (trunk+leader pixels found, far pixels called trunk) judge whether the segmenter
works on real trees; a metric that miscounts would mislead silently. The stand-in is written in tmp in the real
set's format (512×512 RGBA PNG: winter / summer images with depth in alpha over their masks), so the test needs
no ../shared and never reads the real test set; expected values are worked out by hand from the drawn masks.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from branchrange.core.segmentation.choose import make_segmenter

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))
import real_orchard  # noqa: E402
import segmenter as segmenter_benchmark  # noqa: E402


def trunk_mask() -> np.ndarray:
    """`bool 256×256`: a vertical trunk 20 px wide (columns 118–137, rows 60–255) — 3,920 pixels."""
    mask = np.zeros((256, 256), bool)
    mask[60:, 118:138] = True
    return mask


def write_stand_in(folder: Path, ids: list[str]) -> np.ndarray:
    """Samples `ids` in the real set's format under `folder`/samples: a brown trunk on green grass, depth 100 on
    the trunk, 60–200 growing upwards elsewhere (0 = none in the top 40 rows: the sky); both seasons alike.
    Returns the mask drawn."""
    mask = trunk_mask()
    rows = np.arange(256)[:, None] * np.ones((1, 256))
    depth = np.clip(200 - rows * 0.5, 60, 200).astype(np.uint8)
    depth[:40] = 0
    depth[mask] = 100
    bgr = np.zeros((256, 256, 3), np.uint8)
    bgr[:] = (40, 150, 60)
    bgr[mask] = (30, 60, 110)
    bgr[:40] = (230, 200, 150)
    image_tile = np.dstack([bgr, depth])
    mask_tile = np.dstack([np.repeat(mask[..., None] * np.uint8(255), 3, axis=2), np.full((256, 256), 255, np.uint8)])
    grid = np.concatenate(
        [np.concatenate([image_tile, image_tile], axis=1), np.concatenate([mask_tile, mask_tile], axis=1)], axis=0
    )
    (folder / "samples").mkdir(parents=True)
    for sample_id in ids:
        cv2.imwrite(str(folder / "samples" / f"{sample_id}.png"), grid)
    return mask


def test_a_prediction_equal_to_the_mask_finds_all_and_calls_nothing_far() -> None:
    mask = trunk_mask()
    counts = real_orchard.count_pixels(trunk=mask, branch=np.zeros_like(mask), mask=mask)
    assert counts.labelled == counts.found == 20 * 196
    assert counts.far_trunk == counts.far_branch == 0
    assert counts.shares() == {"found_share": 1.0, "far_trunk_share": 0.0, "far_branch_share": 0.0}


def test_far_pixels_begin_more_than_ten_pixels_from_the_mask() -> None:
    """A branch 11 px right of the trunk is far, one 10 px right is not; half found → 50 %."""
    mask = trunk_mask()
    far = real_orchard.far_from(mask)
    assert not far[100, 137 + 10] and far[100, 137 + 11] and far[0, 0]
    trunk = np.zeros_like(mask)
    trunk[60:158, 118:138] = True  # the upper half of the labelled trunk
    branch = np.zeros_like(mask)
    branch[100:110, 147:149] = True  # 10 and 11 px from the mask's edge column 137: 10 pixels far
    counts = real_orchard.count_pixels(trunk, branch, mask)
    assert counts.shares()["found_share"] == pytest.approx(0.5)
    assert (counts.far_trunk, counts.far_branch) == (0, 10)
    assert counts.far == int(np.count_nonzero(far))


def test_relative_disparity_puts_the_trees_median_at_eight_px_and_nothing_where_depth_is_missing() -> None:
    mask = trunk_mask()
    depth = np.full((256, 256), 50, np.uint8)
    depth[mask] = 100
    depth[:10] = 0
    disparity = real_orchard.relative_disparity(depth, mask)
    assert np.median(disparity[mask]) == pytest.approx(8.0)
    assert disparity[20, 0] == pytest.approx(16.0)  # twice as near as the tree: twice its disparity
    assert not disparity[:10].any()
    assert not real_orchard.relative_disparity(np.zeros_like(depth), mask).any()


def test_overlay_ids_are_fixed_by_id_and_spread_over_the_set() -> None:
    ids = [f"R01N{k:02d}" for k in range(20)]
    assert real_orchard.overlay_ids(ids[::-1]) == ["R01N00", "R01N04", "R01N08", "R01N11", "R01N15", "R01N19"]
    assert real_orchard.overlay_ids(ids[:2]) == ["R01N00", "R01N01"]


def test_read_sample_splits_the_tiles_and_refuses_another_shape(tmp_path: Path) -> None:
    mask = write_stand_in(tmp_path, ["R01N01"])
    sample = real_orchard.read_sample(tmp_path / "samples" / "R01N01.png")
    rgb, depth, read_mask = sample["summer"]
    assert np.array_equal(read_mask, mask)
    assert tuple(rgb[200, 0]) == (60, 150, 40)  # RGB of the grass drawn as BGR
    assert depth[0, 0] == 0 and depth[200, 128] == 100
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((8, 8, 4), np.uint8))
    with pytest.raises(ValueError, match="512×512 RGBA"):
        real_orchard.read_sample(tmp_path / "small.png")


def test_the_benchmark_on_two_stand_in_samples_writes_per_sample_figures_and_overlays(tmp_path: Path, capsys) -> None:
    """The shipped learned segmenter through the script's `--real-orchard` path: both seasons and disparity
    modes, per-sample counts that pool to the season's, the mask's own pixel count, overlays of both samples."""
    folder = tmp_path / "real_orchard_rgbd"
    mask = write_stand_in(folder, ["R01N01", "R02U07"])
    out = tmp_path / "out.json"
    tiles_as_they_are = real_orchard.TILE
    assert (
        segmenter_benchmark.main_real_orchard(["learned"], tmp_path / "overlays", out, tiles_as_they_are, folder) == 0
    )
    result = json.loads(out.read_text())["real_orchard"]["learned"]
    assert result["samples"] == 2 and result["overlay_ids"] == ["R01N01", "R02U07"] and result["frame_width"] == 256
    for season in ("winter", "summer"):
        for mode in ("depth", "none"):
            pooled = result["seasons"][season][mode]["final"]
            per_sample = [result["per_sample"][i][season][mode]["final"] for i in ("R01N01", "R02U07")]
            assert pooled["labelled"] == 2 * int(mask.sum())
            assert pooled["found"] == sum(s["found"] for s in per_sample)
            assert pooled["far_trunk"] == sum(s["far_trunk"] for s in per_sample)
            assert pooled["found_share"] == pytest.approx(pooled["found"] / pooled["labelled"])
            assert set(result["seasons"][season][mode]) == {"final", "network"}
    for sample_id in ("R01N01", "R02U07"):
        overlay = cv2.imread(str(tmp_path / "overlays" / f"{sample_id}.jpg"))
        assert overlay.shape == (512, 512, 3)
    printed = capsys.readouterr().out
    assert "winter   depth      final" in printed and "CPU" not in printed  # the CPU line is main's


def test_without_the_data_set_the_benchmark_says_so_and_runs_nothing(tmp_path: Path, capsys) -> None:
    out = tmp_path / "out.json"
    assert segmenter_benchmark.main_real_orchard(["learned"], None, out, folder=tmp_path / "absent") == 0
    assert "no data set at" in capsys.readouterr().err
    assert not out.exists()


def test_tiles_are_seen_as_the_products_frame_with_the_scene_scaled_alike(tmp_path: Path) -> None:
    """Enlarged to 640 px: the image larger, depth and mask by nearest neighbour (no new depth values), the mask's
    share of the frame kept; the benchmark then counts at that size and still draws tile-sized overlays."""
    folder = tmp_path / "real_orchard_rgbd"
    mask = write_stand_in(folder, ["R01N01"])
    rgb, depth, read_mask = real_orchard.read_sample(folder / "samples" / "R01N01.png")["summer"]
    big_rgb, big_depth, big_mask = real_orchard.enlarged(rgb, depth, read_mask, 640)
    assert big_rgb.shape == (640, 640, 3) and big_depth.shape == big_mask.shape == (640, 640)
    assert set(np.unique(big_depth)) <= set(np.unique(depth))
    assert big_mask.mean() == pytest.approx(mask.mean(), rel=0.05)
    assert real_orchard.enlarged(rgb, depth, read_mask, 256)[0] is rgb
    assert real_orchard.tile_geometry(640).focal_px == 320.0  # the ZED Mini's own at 640 px
    result = real_orchard.run_real_orchard(make_segmenter("learned"), folder, tmp_path / "overlays")
    assert result["frame_width"] == real_orchard.PRODUCT_FRAME_WIDTH == 640
    counted = result["seasons"]["summer"]["none"]["final"]
    assert counted["labelled"] == int(big_mask.sum())
    assert cv2.imread(str(tmp_path / "overlays" / "R01N01.jpg")).shape == (512, 512, 3)
