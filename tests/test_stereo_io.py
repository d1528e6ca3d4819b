"""File formats of stereo.io: round trips, the real files in ../shared/data, and clear errors on bad input."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from stereo.io import (
    ArrayFormatError,
    MalformedFileError,
    colorize_disparity,
    read_exr_depth,
    read_grey,
    read_kitti_disparity,
    read_middlebury2001_disparity,
    read_middlebury2001_info,
    read_pfm,
    read_rgb,
    write_exr_depth,
    write_kitti_disparity,
    write_pfm,
    write_rgb,
)


@pytest.fixture
def disparity() -> np.ndarray:
    """A 5×7 float32 map whose rows differ, so a vertical flip would be caught."""
    return (np.arange(35, dtype=np.float32).reshape(5, 7) * 1.25 + 0.5).astype(np.float32)


# ---------------------------------------------------------------- PFM
@pytest.mark.parametrize("little_endian", [True, False])
def test_pfm_round_trip_keeps_values_and_row_order(tmp_path: Path, disparity: np.ndarray, little_endian: bool) -> None:
    path = tmp_path / "d.pfm"
    write_pfm(path, disparity, little_endian=little_endian)
    assert path.read_bytes().startswith(b"Pf\n7 5\n" + (b"-1.0\n" if little_endian else b"1.0\n"))
    np.testing.assert_array_equal(read_pfm(path), disparity)


def test_pfm_is_stored_bottom_up(tmp_path: Path, disparity: np.ndarray) -> None:
    path = tmp_path / "d.pfm"
    write_pfm(path, disparity)
    first_stored = np.frombuffer(path.read_bytes()[-disparity.nbytes :], dtype="<f4")[:7]
    np.testing.assert_array_equal(first_stored, disparity[-1])


def test_pfm_big_endian_written_by_hand_is_read(tmp_path: Path) -> None:
    path = tmp_path / "be.pfm"
    values = [1.5, -2.0, 3.25, 4.0, 5.0, 6.5]  # stored bottom row first
    path.write_bytes(b"Pf\n3 2\n1.0\n" + struct.pack(">6f", *values))
    np.testing.assert_array_equal(read_pfm(path), np.array([[4.0, 5.0, 6.5], [1.5, -2.0, 3.25]], dtype=np.float32))


def test_colour_pfm_reads_channel_zero_or_all_channels(tmp_path: Path, disparity: np.ndarray) -> None:
    colour = np.stack([disparity, disparity * 2, disparity * 3], axis=2)
    path = tmp_path / "c.pfm"
    write_pfm(path, colour)
    assert path.read_bytes().startswith(b"PF\n")
    np.testing.assert_array_equal(read_pfm(path), disparity)
    np.testing.assert_array_equal(read_pfm(path, all_channels=True), colour)


def test_pfm_header_on_one_line_with_crlf_is_read(tmp_path: Path) -> None:
    path = tmp_path / "h.pfm"
    path.write_bytes(b"Pf 2 1 -1.0\r\n" + struct.pack("<2f", 7.0, 8.0))
    np.testing.assert_array_equal(read_pfm(path), np.array([[7.0, 8.0]], dtype=np.float32))


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"P6\n2 1\n255\n" + b"\0" * 6, "magic"),
        (b"Pf\n2 1\n-1.0\n" + b"\0" * 5, "truncated"),
        (b"Pf\n2 x\n-1.0\n" + b"\0" * 8, "not numbers"),
        (b"Pf\n2 1\n0\n" + b"\0" * 8, "non-zero"),
        (b"Pf\n2", "header ends"),
    ],
)
def test_malformed_pfm_raises_naming_the_fault(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.pfm"
    path.write_bytes(content)
    with pytest.raises(MalformedFileError, match=message) as info:
        read_pfm(path)
    assert str(path) in str(info.value)


def test_write_pfm_rejects_a_four_channel_array(tmp_path: Path) -> None:
    with pytest.raises(ArrayFormatError, match="H×W or H×W×3"):
        write_pfm(tmp_path / "x.pfm", np.zeros((2, 2, 4), np.float32))


def test_sceneflow_pfm_reads_as_top_row_first(shared_data: Path) -> None:
    folder = shared_data / "stereo" / "sceneflow_flyingthings3d_train_A_0000_0006"
    disp = read_pfm(folder / "disp_left.pfm")
    assert disp.shape == (540, 960) and disp.dtype == np.float32
    assert np.isfinite(disp).all() and 0 < disp.min() and disp.max() < 400
    # The first stored (little-endian) values belong to the bottom row.
    raw = (folder / "disp_left.pfm").read_bytes()
    bottom_left = struct.unpack("<f", raw[len(raw) - 540 * 960 * 4 :][:4])[0]
    assert disp[-1, 0] == pytest.approx(bottom_left)


# ---------------------------------------------------------------- KITTI
def test_kitti_round_trip_quantises_to_1_256_px_and_keeps_invalid_zero(tmp_path: Path) -> None:
    disp = np.array([[0.0, 1.0, 10.5, np.nan], [-3.0, 100.123, 255.99, np.inf], [1e-4, 0.5, 2.0, 3.0]], np.float32)
    path = tmp_path / "k.png"
    write_kitti_disparity(path, disp)
    back = read_kitti_disparity(path)
    expected = np.array(
        [
            [0.0, 1.0, 10.5, 0.0],
            [0.0, round(100.123 * 256) / 256, round(255.99 * 256) / 256, 0.0],
            [1 / 256, 0.5, 2.0, 3.0],
        ],
        np.float32,
    )
    np.testing.assert_allclose(back, expected, rtol=0, atol=1e-6)


def test_kitti_file_is_16_bit_value_times_256(tmp_path: Path) -> None:
    import cv2

    path = tmp_path / "k.png"
    write_kitti_disparity(path, np.array([[2.5, 0.0]], np.float32))
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.tolist() == [[640, 0]]


def test_kitti_disparity_beyond_256_px_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ArrayFormatError, match="KITTI maximum"):
        write_kitti_disparity(tmp_path / "k.png", np.array([[300.0]], np.float32))


def test_8_bit_png_is_not_a_kitti_disparity(tmp_path: Path) -> None:
    path = tmp_path / "rgb.png"
    write_rgb(path, np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(MalformedFileError, match="16-bit single-channel"):
        read_kitti_disparity(path)


# ---------------------------------------------------------------- EXR
@pytest.mark.parametrize("pixel_type", ["half", "float"])
def test_exr_depth_round_trip_in_centimetres_with_fp16_sky(tmp_path: Path, pixel_type: str) -> None:
    depth_cm = np.array([[150.0, 2048.0, 65504.0], [33.25, 1.0, 900.5]], np.float32)
    path = tmp_path / "depth.exr"
    write_exr_depth(path, depth_cm, pixel_type=pixel_type)
    np.testing.assert_array_equal(read_exr_depth(path), depth_cm)


def test_exr_reader_takes_r_of_a_ue5_style_rgb_file(tmp_path: Path) -> None:
    import OpenEXR

    r = np.array([[120.0, 65504.0]], np.float16)
    nan = np.full_like(r, np.nan)
    path = tmp_path / "ue5.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, {"R": r, "G": nan, "B": nan}) as exr:
        exr.write(str(path))
    depth = read_exr_depth(path)
    assert depth.dtype == np.float32
    np.testing.assert_array_equal(depth, [[120.0, 65504.0]])


@pytest.mark.parametrize(("pixel_type", "dtype"), [("half", np.float16), ("float", np.float32)])
def test_exr_writer_uses_the_ue5_layout_depth_in_r_and_nan_in_g_and_b(
    tmp_path: Path, pixel_type: str, dtype: type
) -> None:
    import OpenEXR

    depth_cm = np.array([[150.0, 65504.0], [33.25, 1.0]], np.float32)
    path = tmp_path / "depth.exr"
    write_exr_depth(path, depth_cm, pixel_type=pixel_type)
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        channels = {name: np.asarray(channel.pixels) for name, channel in exr.channels().items()}
    assert sorted(channels) == ["B", "G", "R"]
    assert all(pixels.dtype == dtype and pixels.shape == (2, 2) for pixels in channels.values())
    assert np.isnan(channels["G"]).all() and np.isnan(channels["B"]).all()
    # the authors read it with OpenCV as a BGR image and take index 2
    bgr = np.stack([channels["B"], channels["G"], channels["R"]], axis=2)
    np.testing.assert_array_equal(bgr[:, :, 2], depth_cm)


def test_exr_without_the_channel_names_the_channels_found(tmp_path: Path) -> None:
    path = tmp_path / "z.exr"
    write_exr_depth(path, np.ones((2, 2), np.float32))
    with pytest.raises(MalformedFileError, match=r"no channel 'Z'.*\['B', 'G', 'R'\]"):
        read_exr_depth(path, channel="Z")


def test_non_exr_file_is_malformed_and_missing_exr_is_not_found(tmp_path: Path) -> None:
    bogus = tmp_path / "bogus.exr"
    bogus.write_bytes(b"not an exr at all")
    with pytest.raises(MalformedFileError, match="not a readable OpenEXR"):
        read_exr_depth(bogus)
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        read_exr_depth(tmp_path / "missing.exr")


# ---------------------------------------------------------------- images
def test_rgb_png_round_trip_keeps_channel_order(tmp_path: Path) -> None:
    image = np.zeros((3, 4, 3), np.uint8)
    image[..., 0] = 200  # pure red must stay in channel 0
    image[1, 2] = (1, 2, 3)
    path = tmp_path / "img.png"
    write_rgb(path, image)
    np.testing.assert_array_equal(read_rgb(path), image)


def test_grey_png_is_read_as_three_equal_channels(tmp_path: Path) -> None:
    path = tmp_path / "g.png"
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    write_rgb(path, grey)
    rgb = read_rgb(path)
    assert rgb.shape == (3, 4, 3)
    for c in range(3):
        np.testing.assert_array_equal(rgb[..., c], grey)
    np.testing.assert_array_equal(read_grey(path), grey)


def test_read_grey_rejects_a_colour_image(tmp_path: Path) -> None:
    path = tmp_path / "c.png"
    write_rgb(path, np.full((2, 2, 3), (10, 20, 30), np.uint8))
    with pytest.raises(MalformedFileError, match="colour pixels"):
        read_grey(path)


def test_unreadable_image_files_raise_clear_errors(tmp_path: Path) -> None:
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"\x89PNG garbage")
    with pytest.raises(MalformedFileError, match="broken.png.*not a readable image"):
        read_rgb(broken)
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(MalformedFileError, match="empty"):
        read_rgb(empty)
    with pytest.raises(FileNotFoundError):
        read_rgb(tmp_path / "nope.png")


def test_write_rgb_rejects_float_images(tmp_path: Path) -> None:
    with pytest.raises(ArrayFormatError, match="uint8"):
        write_rgb(tmp_path / "f.png", np.zeros((2, 2, 3), np.float32))


def test_write_rgb_names_an_extension_without_encoder(tmp_path: Path) -> None:
    with pytest.raises(ArrayFormatError, match=r"no encoder for the extension '\.xyz'"):
        write_rgb(tmp_path / "f.xyz", np.zeros((2, 2, 3), np.uint8))


# ---------------------------------------------------------------- Middlebury 2001
@pytest.mark.parametrize(
    ("scene", "scale", "levels"), [("tsukuba", 16, {0, 80, 96, 112, 128, 160, 176, 224}), ("venus", 8, None)]
)
def test_middlebury_palette_ground_truth_becomes_grey_over_scale(
    shared_data: Path, scene: str, scale: int, levels: set | None
) -> None:
    folder = shared_data / "stereo" / f"middlebury2001_{scene}"
    info = read_middlebury2001_info(folder / "info.txt")
    assert info.scale == scale
    grey = read_grey(folder / "groundtruth.png")
    if levels is not None:
        assert set(np.unique(grey).tolist()) == levels
    disp = read_middlebury2001_disparity(folder / "groundtruth.png", info.scale)
    np.testing.assert_array_equal(disp, grey.astype(np.float32) / scale)
    assert disp.shape == read_rgb(folder / "imL.png").shape[:2]
    assert 0 < disp.max() < info.ndisp + 1  # ndisp integer levels 0..ndisp, sub-pixel steps


def test_middlebury_info_with_one_number_is_malformed(tmp_path: Path) -> None:
    path = tmp_path / "info.txt"
    path.write_text("16\n")
    with pytest.raises(MalformedFileError, match="two integers"):
        read_middlebury2001_info(path)


# ---------------------------------------------------------------- colour map
def test_colorize_marks_invalid_black_and_orders_near_far() -> None:
    disp = np.array([[0.0, np.nan, -1.0, 10.0, 100.0, 300.0]], np.float32)
    rgb = colorize_disparity(disp, max_disp=100.0)
    assert rgb.dtype == np.uint8 and rgb.shape == (1, 6, 3)
    assert (rgb[0, :3] == 0).all()
    assert rgb[0, 3].any()
    far_r, far_b = int(rgb[0, 3, 0]), int(rgb[0, 3, 2])
    near_r, near_b = int(rgb[0, 4, 0]), int(rgb[0, 4, 2])
    assert far_b > far_r and near_r > near_b  # turbo: far blue, near red
    np.testing.assert_array_equal(rgb[0, 5], rgb[0, 4])  # clipped at max_disp


def test_colorize_default_scale_is_the_largest_valid_disparity() -> None:
    disp = np.array([[5.0, 20.0]], np.float32)
    np.testing.assert_array_equal(colorize_disparity(disp), colorize_disparity(disp, max_disp=20.0))
    assert not np.array_equal(colorize_disparity(disp), colorize_disparity(disp, max_disp=40.0))
