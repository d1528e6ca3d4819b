"""Dataset loaders read files in each dataset's real format, and the splits follow the paper's rules."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest
from stereo_training_fixtures import planar_scene, write_virtualtree_layout

from stereo.datasets import (
    DatasetError,
    Eth3dDataset,
    MiddleburyDataset,
    RectifiedPairsDataset,
    SceneFlowDataset,
    SyntheticDataset,
    VirtualTreeDataset,
    open_dataset,
)
from stereo.datasets.splits import group_split, held_out_count, split_train_val
from stereo.datasets.virtualtree import depth_cm_to_disparity, parse_split_line
from stereo.io import (
    read_grey,
    read_middlebury2001_info,
    read_pfm,
    read_rgb,
    write_kitti_disparity,
    write_pfm,
    write_rgb,
)


@pytest.fixture(scope="module")
def scenes():
    return [planar_scene(seed, 48, 80, sky_rows=6) for seed in range(3)]


def test_depth_in_centimetres_becomes_disparity_with_sky_and_bad_values_invalid():
    depth = np.array([[100.0, 65504.0, 65000.0], [np.inf, np.nan, -3.0], [0.0, 64999.0, 6.3]], dtype=np.float32)
    disparity = depth_cm_to_disparity(depth)
    assert disparity[0, 0] == pytest.approx(960 * 6.3 / 100.0)
    assert disparity[2, 1] == pytest.approx(960 * 6.3 / 64999.0)
    assert disparity[2, 2] == pytest.approx(960.0)
    assert np.count_nonzero(disparity) == 3


def test_split_line_with_spaces_in_folder_names_rejoins_six_tokens():
    line = "left image/left_7.png left depth/depth_7.exr right image/right_7.png"
    assert parse_split_line(line) == ("left image/left_7.png", "left depth/depth_7.exr", "right image/right_7.png")
    assert parse_split_line("l/a.png d/a.exr r/a.png") == ("l/a.png", "d/a.exr", "r/a.png")
    with pytest.raises(DatasetError, match=r"val.txt:3: expected 3 paths .* found 4 tokens"):
        parse_split_line("a b c d", source="val.txt", line_no=3)


def test_virtualtree_split_file_pairs_load_with_exact_disparity(tmp_path, scenes):
    root = write_virtualtree_layout(tmp_path / "vt", scenes, {"train": [0, 2], "val": [1]})
    train = VirtualTreeDataset(root, "train")
    assert [r.name for r in train.records] == ["left image/left_0.png", "left image/left_2.png"]
    sample = train[1]
    assert sample["left"].dtype == np.uint8 and sample["left"].shape == (48, 80, 3)
    np.testing.assert_array_equal(sample["left"], scenes[2].left)
    truth = scenes[2].disparity
    assert np.all(sample["disparity"][:6] == 0), "sky rows (depth 65504 cm) must be invalid"
    # EXR stores fp16 depth: relative error ≤ 2^-11 carries over to disparity.
    np.testing.assert_allclose(sample["disparity"][6:], truth[6:], rtol=1e-3)
    assert sample["meta"] == {"dataset": "virtualtree", "name": "left image/left_2.png", "index": 1}
    assert len(VirtualTreeDataset(root)) == 3, "without a split every left_N.png is a pair"


def test_virtualtree_missing_file_is_named(tmp_path, scenes):
    root = write_virtualtree_layout(tmp_path / "vt", scenes, {"train": [0, 1]})
    (root / "left depth" / "depth_1.exr").unlink()
    with pytest.raises(DatasetError, match=r"depth_1.exr: listed for pair 'left image/left_1.png' but not found"):
        VirtualTreeDataset(root, "train")
    with pytest.raises(DatasetError, match=r"split 'nosuch': no such file"):
        VirtualTreeDataset(root, "nosuch")


def test_synthetic_set_from_emcstereo_synth_uses_its_own_rig(tmp_path):
    from stereo.synth.camera import SynthCamera
    from stereo.synth.render import render_scene
    from stereo.synth.writer import scene_seed, write_dataset

    summary = write_dataset(tmp_path / "syn", scenes=2, seed=3, width=256, height=96, progress=False)
    dataset = SyntheticDataset(summary.root, "train")
    index = summary.splits["train"][0]
    truth = render_scene(scene_seed(3, index), SynthCamera.zed_mini(256, 96))
    sample = dataset[0]
    valid = truth.disparity > 0
    np.testing.assert_array_equal(sample["disparity"] > 0, valid)
    np.testing.assert_allclose(sample["disparity"][valid], truth.disparity[valid], rtol=1e-5)
    np.testing.assert_array_equal(sample["left"], truth.left)


#: Where the authors' SceneFlow layout keeps one frame of each subset: (frames, disparity, sequence folder).
SCENEFLOW_PLACES = [
    ("flyingthings3d__frames", "flyingthings3d_disparity", "A/0000"),
    ("monkaa__frames", "monkaa_disparity", "a_rain_of_stones_x2"),
    ("driving__frames", "driving__disparity", "15mm_focallength/scene_forwards/fast"),
]


def _sceneflow_layout(root: Path, shared: Path) -> Path:
    """The shared FlyingThings3D pair placed where each SceneFlow subset of the authors' layout expects a frame."""
    src = shared / "stereo" / "sceneflow_flyingthings3d_train_A_0000_0006"
    for frames, disparities, seq in SCENEFLOW_PLACES:
        for view in ("left", "right"):
            (root / frames / seq / view).mkdir(parents=True)
            (root / frames / seq / view / "0006.png").symlink_to(src / f"{view}_cleanpass.png")
        (root / disparities / seq / "left").mkdir(parents=True)
        (root / disparities / seq / "left" / "0006.pfm").symlink_to(src / "disp_left.pfm")
    return root


def test_sceneflow_reads_the_real_flyingthings_pfm_in_all_three_subset_layouts(tmp_path, shared_data):
    root = _sceneflow_layout(tmp_path / "sf", shared_data)
    dataset = SceneFlowDataset(root)
    assert dataset.names() == [
        "flyingthings3d/A/0000/0006",
        "monkaa/a_rain_of_stones_x2/0006",
        "driving/15mm_focallength/scene_forwards/fast/0006",
    ]
    expected = read_pfm(root / "flyingthings3d_disparity/A/0000/left/0006.pfm")
    for index in range(3):
        sample = dataset[index]
        assert sample["left"].shape == (540, 960, 3) and sample["disparity"].shape == (540, 960)
        np.testing.assert_array_equal(sample["disparity"], np.where(expected > 0, expected, 0))
    assert 0 < float(np.median(sample["disparity"])) < 192


def test_sceneflow_without_subsets_is_an_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no SceneFlow pairs found; expected one of flyingthings3d__frames/"):
        SceneFlowDataset(tmp_path / "empty")


def test_kitti_uint16_png_over_256_with_zero_invalid(tmp_path, scenes):
    root = tmp_path / "kitti"
    for sub in ("left", "right", "ground_truth"):
        (root / sub).mkdir(parents=True)
    truth = scenes[0].disparity.copy()
    truth[10:14, 20:30] = 0.0
    write_rgb(root / "left" / "000000_10.png", scenes[0].left)
    write_rgb(root / "right" / "000000_10.png", scenes[0].right)
    write_kitti_disparity(root / "ground_truth" / "000000_10.png", truth)
    write_rgb(root / "left" / "000001_10.png", scenes[1].left)  # no partner: not a pair
    dataset = open_dataset("kitti2012", root)
    assert dataset.name == "kitti2012" and dataset.names() == ["000000_10"]
    disparity = dataset[0]["disparity"]
    np.testing.assert_allclose(disparity, truth, atol=1 / 256)
    assert np.all(disparity[10:14, 20:30] == 0)


def test_eth3d_pfm_with_inf_unknown_becomes_zero(tmp_path, scenes):
    root = tmp_path / "eth3d"
    (root / "two_view_training" / "delivery_area_1l").mkdir(parents=True)
    (root / "two_view_training_disparity" / "delivery_area_1l").mkdir(parents=True)
    write_rgb(root / "two_view_training/delivery_area_1l/im0.png", scenes[1].left)
    write_rgb(root / "two_view_training/delivery_area_1l/im1.png", scenes[1].right)
    truth = scenes[1].disparity.copy()
    truth[:6] = np.inf
    write_pfm(root / "two_view_training_disparity/delivery_area_1l/disp0GT.pfm", truth)
    sample = Eth3dDataset(root)[0]
    assert np.all(sample["disparity"][:6] == 0)
    np.testing.assert_array_equal(sample["disparity"][6:], truth[6:])


def test_middlebury_pfm_masks_192_and_more(tmp_path, scenes):
    scene = tmp_path / "mb" / "Adirondack"
    scene.mkdir(parents=True)
    write_rgb(scene / "im0.png", scenes[2].left)
    write_rgb(scene / "im1.png", scenes[2].right[:, :-1])  # one pixel narrower: cropped to the common size
    truth = scenes[2].disparity * 6.0
    write_pfm(scene / "disp0.pfm", truth)
    sample = MiddleburyDataset(tmp_path / "mb")[0]
    assert sample["disparity"].shape == (48, 79)
    expected = np.where(truth < 192, truth, 0)[:, :79]
    np.testing.assert_array_equal(sample["disparity"], expected)
    assert np.any(truth >= 192) and np.any(expected > 0)


def test_middlebury_2001_real_pairs_scaled_by_info(shared_data):
    root = shared_data / "stereo"
    for name in ("middlebury2001_tsukuba", "middlebury2001_venus"):
        scene = root / name
        sample = MiddleburyDataset(scene)[0]
        scale = read_middlebury2001_info(scene / "info.txt").scale
        grey = read_grey(scene / "groundtruth.png")
        np.testing.assert_allclose(sample["disparity"], grey.astype(np.float32) / scale)
        np.testing.assert_array_equal(sample["left"], read_rgb(scene / "imL.png"))
        assert 0 < sample["disparity"].max() < 64


def test_unlabelled_pairs_have_no_ground_truth(tmp_path, scenes):
    for sub in ("left", "right"):
        (tmp_path / sub).mkdir()
    write_rgb(tmp_path / "left" / "f0.png", scenes[0].left)
    write_rgb(tmp_path / "right" / "f0.png", scenes[0].right)
    sample = RectifiedPairsDataset(tmp_path)[0]
    assert sample["disparity"].shape == (48, 80) and not sample["disparity"].any()


def test_open_dataset_names_the_missing_folder(tmp_path):
    with pytest.raises(DatasetError, match=r"kitti/left: folder not found; expected KITTI left images"):
        open_dataset("kitti2015", tmp_path / "kitti")
    with pytest.raises(DatasetError, match="has no split files"):
        open_dataset("eth3d", tmp_path, split="train")


@pytest.mark.parametrize("n, n_val", [(194, 19), (200, 20), (27, 3), (35454, 3545), (3, 1)])
def test_paper_split_holds_out_round_ten_percent_with_seed_zero(n, n_val):
    train, val = split_train_val(n)
    order = list(range(n))
    random.Random(0).shuffle(order)
    assert len(val) == n_val == held_out_count(n, 0.1)
    assert val == sorted(order[:n_val])
    assert sorted(train + val) == list(range(n))


def test_group_split_keeps_every_tree_on_one_side():
    names = [f"left image/tree{t:02d}_frame{f}.png" for t in range(10) for f in range(4)]
    train, val = group_split(names, r"tree(\d+)_", 0.2, seed=0)
    trees = lambda idx: {names[i].split("/")[1].split("_")[0] for i in idx}  # noqa: E731
    assert len(trees(val)) == 2 and not trees(train) & trees(val)
    assert len(val) == 8 and len(train) == 32
    assert group_split(names, r"tree(\d+)_", 0.2, seed=0) == (train, val)
    with pytest.raises(DatasetError, match=r"group pattern .*scene.* does not match record name"):
        group_split(names, r"scene(\d+)")
    with pytest.raises(DatasetError, match=r"group pattern 'tree\(': not a valid regular expression"):
        group_split(names, "tree(")
