"""The synthetic dataset on disk: VirtualTree layout and split format, EXR in cm, masks, JSON, determinism, CLI."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from stereo.cli import main as emcstereo
from stereo.io import read_exr_depth, read_rgb
from stereo.synth import SynthCamera, render_scene
from stereo.synth.writer import SKY_DEPTH_CM, SynthWriteError, scene_seed, split_indices, write_dataset

WIDTH, HEIGHT = 160, 96


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synth") / "Virtual_branches_data"
    write_dataset(root, 10, 7, WIDTH, HEIGHT, progress=False)
    return root


def read_authors_split(path: Path) -> list[tuple[str, str, str]]:
    """The authors' parser: six whitespace tokens rejoined pairwise into (left, depth, right)."""
    triples = []
    for line in path.read_text(encoding="utf-8").splitlines():
        tokens = line.split()
        assert len(tokens) == 6, line
        triples.append((f"{tokens[0]} {tokens[1]}", f"{tokens[2]} {tokens[3]}", f"{tokens[4]} {tokens[5]}"))
    return triples


def file_digests(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_split_files_parse_in_the_authors_six_token_format_and_cover_all_scenes(dataset):
    seen = []
    for name, expected in (("train", 8), ("val", 1), ("test", 1)):
        triples = read_authors_split(dataset / f"virtualtree_{name}.txt")
        assert len(triples) == expected
        for left, depth, right in triples:
            n = int(left.split("_")[-1].split(".")[0])
            assert (left, depth, right) == (
                f"left image/left_{n}.png",
                f"left depth/depth_{n}.exr",
                f"right image/right_{n}.png",
            )
            assert all((dataset / p).is_file() for p in (left, depth, right))
            seen.append(n)
    assert sorted(seen) == list(range(10))


def test_split_indices_are_80_10_10_sorted_and_disjoint():
    splits = split_indices(100, 3)
    assert [len(splits[k]) for k in ("train", "val", "test")] == [80, 10, 10]
    assert all(v == sorted(v) for v in splits.values())
    assert sorted(sum(splits.values(), [])) == list(range(100))


def test_exr_holds_depth_in_centimetres_with_sky_at_65504(dataset):
    scene = render_scene(scene_seed(7, 4), SynthCamera.zed_mini(WIDTH, HEIGHT))
    depth_cm = read_exr_depth(dataset / "left depth" / "depth_4.exr")
    finite = np.isfinite(scene.depth_m)
    assert np.allclose(depth_cm[finite], scene.depth_m[finite] * 100.0, rtol=1e-6)
    assert np.all(depth_cm[~finite] == SKY_DEPTH_CM)
    assert np.array_equal(read_rgb(dataset / "left image" / "left_4.png"), scene.left)
    assert np.array_equal(read_rgb(dataset / "right image" / "right_4.png"), scene.right)


def test_depth_exr_has_the_ue5_channel_layout_r_depth_g_and_b_nan(dataset):
    import OpenEXR

    with OpenEXR.File(str(dataset / "left depth" / "depth_4.exr"), separate_channels=True) as exr:
        channels = {name: np.asarray(channel.pixels) for name, channel in exr.channels().items()}
    assert sorted(channels) == ["B", "G", "R"]
    assert np.isnan(channels["G"]).all() and np.isnan(channels["B"]).all()
    # the authors' loader: OpenCV's BGR order, channel index 2 is the depth in cm
    bgr = np.stack([channels["B"], channels["G"], channels["R"]], axis=2)
    np.testing.assert_array_equal(bgr[:, :, 2], read_exr_depth(dataset / "left depth" / "depth_4.exr"))
    assert np.isfinite(bgr[:, :, 2]).all() and bgr[:, :, 2].min() > 0


def test_virtualtree_loader_reads_the_set_through_its_split_files(dataset):
    virtualtree = pytest.importorskip("stereo.datasets.virtualtree", reason="VirtualTree loader not importable")
    camera = SynthCamera.zed_mini(WIDTH, HEIGHT)
    data = virtualtree.VirtualTreeDataset(
        dataset, "train", focal_px=camera.focal_px, baseline_cm=camera.baseline_m * 100.0
    )
    assert len(data) == 8
    first = int(Path(data.records[0].left).stem.split("_")[1])
    sample = data[0]
    scene = render_scene(scene_seed(7, first), camera)
    assert np.array_equal(sample["left"], scene.left)
    assert np.allclose(sample["disparity"], scene.disparity, rtol=1e-5, atol=1e-6)


def test_synthetic_dataset_reads_the_rig_from_synth_json(dataset):
    synthetic = pytest.importorskip("stereo.datasets.synthetic", reason="synthetic dataset loader not importable")
    data = synthetic.SyntheticDataset(dataset, "val")
    assert len(data) == 1
    index = int(Path(data.records[0].left).stem.split("_")[1])
    scene = render_scene(scene_seed(7, index), SynthCamera.zed_mini(WIDTH, HEIGHT))
    assert np.allclose(data[0]["disparity"], scene.disparity, rtol=1e-5, atol=1e-6)


def test_mask_png_is_16_bit_and_branches_json_carries_camera_and_truth(dataset):
    scene = render_scene(scene_seed(7, 2), SynthCamera.zed_mini(WIDTH, HEIGHT))
    mask = cv2.imread(str(dataset / "masks" / "mask_2.png"), cv2.IMREAD_UNCHANGED)
    assert mask.dtype == np.uint16 and np.array_equal(mask, scene.instance_mask)
    record = json.loads((dataset / "branches" / "branches_2.json").read_text())
    assert record["camera"]["focal_px"] == pytest.approx(WIDTH / 2)
    assert record["camera"]["baseline_m"] == pytest.approx(0.063)
    assert (record["camera"]["width"], record["camera"]["height"]) == (WIDTH, HEIGHT)
    assert record["instance_ids"]["trunk"] == 65535
    assert len(record["branches"]) == len(scene.branches)
    for stored, truth in zip(record["branches"], scene.branches):
        assert stored["id"] == truth.id
        assert np.allclose(stored["cut_point_m"], truth.cut_point_m)
        assert np.allclose(stored["base_m"], truth.base_m) and np.allclose(stored["direction"], truth.direction)
        assert stored["base_radius_m"] == pytest.approx(truth.base_radius_m)


def test_same_seed_writes_byte_identical_files(tmp_path):
    write_dataset(tmp_path / "a", 3, 5, 96, 64, progress=False)
    write_dataset(tmp_path / "b", 3, 5, 96, 64, progress=False)
    write_dataset(tmp_path / "c", 3, 6, 96, 64, progress=False)
    a, b, c = (file_digests(tmp_path / name) for name in "abc")
    assert a == b and len(a) == 3 * 5 + 3 + 1
    assert a["left image/left_0.png"] != c["left image/left_0.png"]


def test_half_exr_stores_fp16_like_ue5_with_sky_at_fp16_max(tmp_path):
    import OpenEXR

    write_dataset(tmp_path, 1, 2, 96, 64, exr_pixel_type="half", progress=False)
    with OpenEXR.File(str(tmp_path / "left depth" / "depth_0.exr"), separate_channels=True) as exr:
        depth = np.asarray(exr.channels()["R"].pixels)
    assert depth.dtype == np.float16
    scene = render_scene(scene_seed(2, 0), SynthCamera.zed_mini(96, 64))
    sky = ~np.isfinite(scene.depth_m)
    assert np.all(depth[sky] == np.float16(65504))
    assert np.allclose(depth[~sky], scene.depth_m[~sky] * 100.0, rtol=1e-3)


def test_write_dataset_shows_a_progress_bar(tmp_path, capsys):
    write_dataset(tmp_path, 2, 0, 64, 64, progress=True)
    err = capsys.readouterr().err
    assert "synth scenes" in err and "2/2" in err


def test_write_dataset_rejects_bad_arguments(tmp_path):
    with pytest.raises(SynthWriteError, match="scenes"):
        write_dataset(tmp_path, 0, 0, 96, 64, progress=False)
    with pytest.raises(SynthWriteError, match="exr_pixel_type"):
        write_dataset(tmp_path, 1, 0, 96, 64, exr_pixel_type="double", progress=False)


def test_synth_command_writes_dataset_and_preview(tmp_path, capsys):
    preview = tmp_path / "preview.png"
    status = emcstereo(
        [
            "synth",
            "--out",
            str(tmp_path / "set"),
            "--scenes",
            "2",
            "--seed",
            "1",
            "--size",
            "96x64",
            "--leaf-shape",
            "needles",
            "--orchard-hardware",
            "--preview",
            str(preview),
            "--quiet",
        ]
    )
    assert status == 0
    assert "wrote 2 scenes" in capsys.readouterr().out
    assert (tmp_path / "set" / "left image" / "left_1.png").is_file()
    assert json.loads((tmp_path / "set" / "branches" / "branches_1.json").read_text())["leaf_shape"] == "needles"
    options = json.loads((tmp_path / "set" / "synth.json").read_text())["options"]
    assert options["leaf_shape"] == "needles" and options["orchard_hardware"] is True
    picture = read_rgb(preview)
    assert picture.shape == (2 * 64, 4 * 96, 3)


def test_synth_command_names_an_out_of_range_option():
    with pytest.raises(SystemExit, match="cut_offset_m"):
        emcstereo(["synth", "--preview", "x.png", "--cut-offset", "0.5"])


def test_synth_command_rejects_malformed_size(capsys):
    with pytest.raises(SystemExit):
        emcstereo(["synth", "--preview", "x.png", "--size", "640by360"])
    assert "WIDTHxHEIGHT" in capsys.readouterr().err


def test_synth_command_names_an_unwritable_output(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    with pytest.raises(SystemExit, match=r"cannot write the dataset under --out .*a_file"):
        emcstereo(["synth", "--out", str(blocker / "set"), "--scenes", "1", "--size", "64x64", "--quiet"])
    with pytest.raises(SystemExit, match=r"--preview .*p\.xyz: no image format"):
        emcstereo(["synth", "--preview", str(tmp_path / "p.xyz")])


def test_synth_command_rejects_an_oversized_image(capsys):
    with pytest.raises(SystemExit):
        emcstereo(["synth", "--preview", "x.png", "--size", "100000x360"])
    assert "at most 4096 px" in capsys.readouterr().err
