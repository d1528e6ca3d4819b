"""Calibration loaders on the real files of ../shared/data and on files written here in the real formats."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from camera import (
    CalibrationError,
    StereoCalibration,
    detect_format,
    from_depthai_json,
    from_kitti,
    from_opencv_file,
    from_rectified,
    from_zed_conf,
    load_calibration,
    write_opencv_file,
)
from camera.depthai_json import calibrated_size
from camera.zed_conf import available_resolutions

ZED_FILES = ("SN1010", "SN14966", "SN1499")


@pytest.fixture(scope="module")
def zed_dir(shared_data: Path) -> Path:
    return shared_data / "calibration" / "zed"


@pytest.fixture(scope="module")
def kitti_file(shared_data: Path) -> Path:
    return shared_data / "calibration" / "kitti" / "2011_09_26_calib_cam_to_cam.txt"


def _write(tmp_path: Path, name: str, text: str, newline: str = "\n") -> Path:
    path = tmp_path / name
    path.write_bytes(text.replace("\n", newline).encode("utf-8"))
    return path


# ---------------------------------------------------------------- ZED factory files (real)


@pytest.mark.parametrize("serial", ZED_FILES)
@pytest.mark.parametrize(
    "resolution, size", [("2K", (2208, 1242)), ("FHD", (1920, 1080)), ("HD", (1280, 720)), ("VGA", (672, 376))]
)
def test_zed_conf_real_files_load_every_resolution(
    zed_dir: Path, serial: str, resolution: str, size: tuple[int, int]
) -> None:
    calib = from_zed_conf(zed_dir / f"{serial}.conf", resolution)
    assert calib.image_size == size
    assert calib.baseline_m == pytest.approx(0.120, abs=0.0005)
    assert calib.T[0] < 0  # right camera to the right: OpenCV's x_right = R x_left + T
    assert 0.25 * size[0] < calib.K1[0, 0] < 1.5 * size[0]
    assert calib.D1.shape == (5,)


def test_zed_conf_with_bom_parses_and_reads_baseline_spelling(zed_dir: Path) -> None:
    path = zed_dir / "SN1499.conf"
    assert path.read_bytes().startswith(b"\xef\xbb\xbf")
    calib = from_zed_conf(path, "HD")
    assert calib.K1[0, 0] == 699.056 and calib.K1[0, 2] == 645.777  # first key after the BOM'd header
    assert calib.baseline_m == pytest.approx(0.120119)  # spelled BaseLine in this file
    np.testing.assert_allclose(calib.D1, [-0.172966, 0.0276472, 0, 0, 0])  # no p1/p2/k3 in the file


def test_zed_conf_rotation_is_rodrigues_of_rx_cv_rz(zed_dir: Path) -> None:
    calib = from_zed_conf(zed_dir / "SN1010.conf", "FHD")
    vector = cv2.Rodrigues(calib.R)[0].ravel()
    np.testing.assert_allclose(vector, [0.00497864, 0.00958521, -0.00185401], rtol=1e-6)


def test_zed_conf_with_crlf_matches_lf(zed_dir: Path, tmp_path: Path) -> None:
    text = (zed_dir / "SN1010.conf").read_text()
    crlf = _write(tmp_path, "crlf.conf", text, "\r\n")
    assert b"\r\n" in crlf.read_bytes()
    assert from_zed_conf(crlf, "HD") == from_zed_conf(zed_dir / "SN1010.conf", "HD")


def test_zed_conf_prefers_ty_per_resolution_over_plain_ty(zed_dir: Path, tmp_path: Path) -> None:
    text = (zed_dir / "SN1010.conf").read_text()
    text = text.replace("TY=0\nTZ=0\n", "TY_HD=0.7\nTZ_HD=-0.3\nTY=1.5\nTZ=0.2\n")
    path = _write(tmp_path, "ty.conf", text)
    np.testing.assert_allclose(from_zed_conf(path, "HD").T, [-0.120, -0.0007, 0.0003])
    np.testing.assert_allclose(from_zed_conf(path, "VGA").T, [-0.120, -0.0015, -0.0002])


def test_zed_conf_accepts_zed_mode_names(zed_dir: Path) -> None:
    assert from_zed_conf(zed_dir / "SN14966.conf", "hd720") == from_zed_conf(zed_dir / "SN14966.conf", "HD")
    assert available_resolutions(zed_dir / "SN14966.conf") == ["2K", "FHD", "HD", "VGA"]


def _hd_only_conf(zed_dir: Path) -> str:
    text = (zed_dir / "SN1010.conf").read_text()
    keep = []
    for block in text.split("\n\n"):
        if block.startswith("[") and not any(tag in block for tag in ("_HD]", "[STEREO]")):
            continue
        keep.append(block)
    return "\n\n".join(keep)


def test_zed_conf_missing_resolution_names_file_and_available(zed_dir: Path, tmp_path: Path) -> None:
    path = _write(tmp_path, "SN_hd.conf", _hd_only_conf(zed_dir))
    with pytest.raises(CalibrationError) as info:
        from_zed_conf(path, "VGA")
    message = str(info.value)
    assert str(path) in message and "LEFT_CAM_VGA" in message and "HD" in message


def test_zed_conf_unknown_resolution_is_rejected(zed_dir: Path) -> None:
    with pytest.raises(CalibrationError, match="resolution.*4K"):
        from_zed_conf(zed_dir / "SN1010.conf", "4K")


@pytest.mark.parametrize(
    "old, new, key, expected",
    [
        ("[STEREO]\nBaseline=120", "[NOT_STEREO]\nBaseline=120", "[STEREO]", "section"),
        ("fy=700.82\n", "", "[LEFT_CAM_HD] fy", "pixels"),
        ("Baseline=120", "Other=120", "[STEREO] baseline", "mm"),
        ("fx=698.76", "fx=nan", "[RIGHT_CAM_HD] fx", "finite"),
        ("cx=665.465", "cx=665,465", "[LEFT_CAM_HD] cx", "'.'"),
        ("RX_HD=0.00497864", "RX_VGA2=1", "rx_hd", "radians"),
    ],
)
def test_zed_conf_bad_input_names_key_and_expectation(
    zed_dir: Path, tmp_path: Path, old: str, new: str, key: str, expected: str
) -> None:
    text = (zed_dir / "SN1010.conf").read_text()
    assert old in text
    path = _write(tmp_path, "bad.conf", text.replace(old, new, 1))
    with pytest.raises(CalibrationError) as info:
        from_zed_conf(path, "HD")
    message = str(info.value)
    assert str(path) in message and key in message and expected in message


def test_missing_file_is_a_calibration_error(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="cannot be read"):
        from_zed_conf(tmp_path / "SN0.conf", "HD")


# ---------------------------------------------------------------- OpenCV FileStorage


@pytest.fixture
def zed_hd(zed_dir: Path) -> StereoCalibration:
    return from_zed_conf(zed_dir / "SN14966.conf", "HD")


@pytest.mark.parametrize("suffix", [".yaml", ".json", ".xml"])
def test_opencv_file_round_trip_is_exact(zed_hd: StereoCalibration, tmp_path: Path, suffix: str) -> None:
    path = write_opencv_file(zed_hd, tmp_path / f"calib{suffix}")
    loaded = from_opencv_file(path)
    assert loaded == zed_hd
    assert detect_format(path) == "opencv"


def test_opencv_json_with_plain_lists_and_stereo_calib_names(zed_hd: StereoCalibration, tmp_path: Path) -> None:
    path = tmp_path / "plain.json"
    path.write_text(
        json.dumps(
            {
                "M1": zed_hd.K1.tolist(),
                "D1": zed_hd.D1.tolist(),
                "M2": zed_hd.K2.tolist(),
                "D2": zed_hd.D2.tolist(),
                "R": zed_hd.R.tolist(),
                "T": zed_hd.T.tolist(),
            }
        )
    )
    loaded = from_opencv_file(path, size=(1280, 720))
    assert loaded == zed_hd


def test_opencv_file_without_size_names_image_width(zed_hd: StereoCalibration, tmp_path: Path) -> None:
    path = tmp_path / "nosize.json"
    path.write_text(
        json.dumps(
            {
                "K1": zed_hd.K1.tolist(),
                "D1": [0, 0, 0, 0],
                "K2": zed_hd.K2.tolist(),
                "D2": [0, 0, 0, 0],
                "R": np.eye(3).tolist(),
                "T": [-0.1, 0, 0],
            }
        )
    )
    with pytest.raises(CalibrationError, match="image_width"):
        from_opencv_file(path)


def test_opencv_file_in_millimetres_is_rejected(zed_hd: StereoCalibration, tmp_path: Path) -> None:
    path = tmp_path / "mm.json"
    path.write_text(
        json.dumps(
            {
                "K1": zed_hd.K1.tolist(),
                "D1": [0] * 5,
                "K2": zed_hd.K2.tolist(),
                "D2": [0] * 5,
                "R": np.eye(3).tolist(),
                "T": [-63.0, 0, 0],
                "image_width": 1280,
                "image_height": 720,
            }
        )
    )
    with pytest.raises(CalibrationError, match=r"T: .*metres"):
        from_opencv_file(path)


def test_opencv_file_missing_key_and_bad_shape(zed_hd: StereoCalibration, tmp_path: Path) -> None:
    good = {
        "K1": zed_hd.K1.tolist(),
        "D1": [0] * 5,
        "K2": zed_hd.K2.tolist(),
        "D2": [0] * 5,
        "R": np.eye(3).tolist(),
        "T": [-0.06, 0, 0],
        "image_width": 1280,
        "image_height": 720,
    }
    missing = tmp_path / "missing.json"
    missing.write_text(json.dumps({k: v for k, v in good.items() if k != "D2"}))
    with pytest.raises(CalibrationError, match=r"D2: key is missing"):
        from_opencv_file(missing)
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps({**good, "K2": [1.0, 2.0]}))
    with pytest.raises(CalibrationError, match=r"K2: holds 2 numbers .*9 numbers"):
        from_opencv_file(wrong)
    infinite = tmp_path / "inf.yaml"
    infinite.write_text(
        "%YAML:1.0\n---\n"
        + "\n".join(f"{k}: {json.dumps(v)}" for k, v in {**good, "D1": [0, 0, 0, 0, 1e999]}.items()).replace(
            "Infinity", ".Inf"
        )
    )
    with pytest.raises(CalibrationError, match=r"D1: .*non-finite"):
        from_opencv_file(infinite)


# ---------------------------------------------------------------- depthai calibration JSON


@pytest.fixture(scope="module")
def oak_handler():
    """A CalibrationHandler filled like an OAK-D's EEPROM (mono pair B/C at 1280×800, RGB on A)."""
    dai = pytest.importorskip("depthai", reason="depthai is needed to write the calibration JSON in its real format")
    socket = dai.CameraBoardSocket
    handler = dai.CalibrationHandler()
    handler.setCameraIntrinsics(socket.CAM_B, [[801.2, 0, 642.5], [0, 800.7, 398.1], [0, 0, 1]], 1280, 800)
    handler.setCameraIntrinsics(socket.CAM_C, [[799.6, 0, 637.9], [0, 799.9, 403.4], [0, 0, 1]], 1280, 800)
    handler.setCameraIntrinsics(socket.CAM_A, [[3070.0, 0, 2028.0], [0, 3068.0, 1520.0], [0, 0, 1]], 4056, 3040)
    for cam in (socket.CAM_A, socket.CAM_B, socket.CAM_C):
        handler.setDistortionCoefficients(cam, [-3.1, 11.2, 0.0008, -0.0004, 9.8, -3.0, 11.0, 9.9] + [0.0] * 6)
    rotation_bc = cv2.Rodrigues(np.array([0.0011, 0.0052, 0.0039]))[0].tolist()
    handler.setCameraExtrinsics(socket.CAM_B, socket.CAM_C, rotation_bc, [-7.503, 0.021, -0.087], [-7.5, 0, 0])
    handler.setCameraExtrinsics(socket.CAM_C, socket.CAM_A, np.eye(3).tolist(), [3.75, -0.02, 0.1], [3.75, 0, 0])
    handler.setStereoLeft(socket.CAM_B, np.eye(3).tolist())
    handler.setStereoRight(socket.CAM_C, np.eye(3).tolist())
    return dai, handler


@pytest.fixture
def oak_json(oak_handler, tmp_path: Path) -> Path:
    _, handler = oak_handler
    path = tmp_path / "oak_calib.json"
    assert handler.eepromToJsonFile(str(path))
    return path


@pytest.mark.parametrize("size", [(1280, 800), (640, 400), (1280, 720), (640, 480)])
def test_depthai_json_intrinsics_match_depthai_scaling(oak_handler, oak_json: Path, size: tuple[int, int]) -> None:
    dai, handler = oak_handler
    calib = from_depthai_json(oak_json, "CAM_B", "CAM_C", size)
    assert calib.image_size == size
    expected_left = np.array(handler.getCameraIntrinsics(dai.CameraBoardSocket.CAM_B, size[0], size[1]))
    expected_right = np.array(handler.getCameraIntrinsics(dai.CameraBoardSocket.CAM_C, size[0], size[1]))
    np.testing.assert_allclose(calib.K1, expected_left, rtol=1e-5)
    np.testing.assert_allclose(calib.K2, expected_right, rtol=1e-5)
    np.testing.assert_allclose(calib.D1, handler.getDistortionCoefficients(dai.CameraBoardSocket.CAM_B), rtol=1e-6)


def test_depthai_json_extrinsics_are_metres_left_to_right(oak_handler, oak_json: Path) -> None:
    dai, handler = oak_handler
    calib = from_depthai_json(oak_json, size=(640, 400))  # the file's stereo pair: B → C
    expected = np.array(handler.getCameraExtrinsics(dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C))
    np.testing.assert_allclose(calib.R, expected[:3, :3], atol=1e-6)
    np.testing.assert_allclose(calib.T, expected[:3, 3] / 100.0, atol=1e-7)
    assert calib.T[0] == pytest.approx(-0.07503, abs=1e-6)


def test_depthai_json_chains_extrinsics_through_other_cameras(oak_handler, oak_json: Path) -> None:
    dai, handler = oak_handler
    calib = from_depthai_json(oak_json, "CAM_A", "CAM_B", (1280, 720))  # A has no link of its own: B → C → A
    expected = np.array(handler.getCameraExtrinsics(dai.CameraBoardSocket.CAM_A, dai.CameraBoardSocket.CAM_B))
    np.testing.assert_allclose(calib.R, expected[:3, :3], atol=1e-5)
    np.testing.assert_allclose(calib.T, expected[:3, 3] / 100.0, atol=1e-6)
    assert load_calibration(oak_json, size=(640, 400)) == from_depthai_json(oak_json, 1, 2, (640, 400))


def test_depthai_calibrated_size_is_each_sockets_own(oak_json: Path) -> None:
    data = json.loads(oak_json.read_text())
    assert calibrated_size(data, "CAM_B", "eeprom") == (1280, 800)
    assert calibrated_size(data, 0, "eeprom") == (4056, 3040)
    with pytest.raises(CalibrationError, match=r"eeprom: socket: unknown camera socket 'CAM_Q'"):
        calibrated_size(data, "CAM_Q", "eeprom")


def test_depthai_json_errors_name_socket_and_key(oak_json: Path, tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match=r"cameraData socket 4: is missing .*\[0, 1, 2\]"):
        from_depthai_json(oak_json, "CAM_B", "CAM_E")
    data = json.loads(oak_json.read_text())
    for socket, entry in data["cameraData"]:
        if socket == 2:
            entry["intrinsicMatrix"] = [[1.0, 0.0], [0.0, 1.0]]
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"cameraData\[2\]\.intrinsicMatrix: has shape \(2, 2\)"):
        from_depthai_json(broken)
    with pytest.raises(CalibrationError, match="unknown camera socket"):
        from_depthai_json(oak_json, "CAM_Q")


@pytest.mark.parametrize(
    "edit, key, expected",
    [
        (lambda d: d["cameraData"][0].__setitem__(0, "left"), r"cameraData\[0\]\[0\]", "socket number"),
        (
            lambda d: d["cameraData"][1][1].__setitem__("cameraType", "fisheye"),
            r"cameraData\[1\]\.cameraType",
            r"0 \(perspective\)",
        ),
        (
            lambda d: d["cameraData"][1][1].__setitem__("distortionCoeff", ["k1"] * 14),
            r"cameraData\[1\]\.distortionCoeff",
            "14 OpenCV distortion",
        ),
        (
            lambda d: d["cameraData"][1][1]["extrinsics"].__setitem__("toCameraSocket", "C"),
            r"cameraData\[1\]\.extrinsics\.toCameraSocket",
            "socket number",
        ),
        (
            lambda d: d["cameraData"][1][1]["extrinsics"].__setitem__("lengthUnit", "cm"),
            r"cameraData\[1\]\.extrinsics\.lengthUnit",
            r"one of \[0, 1, 2, 3, 4\]",
        ),
        (
            lambda d: d["stereoRectificationData"].__setitem__("leftCameraSocket", "B"),
            r"stereoRectificationData\.leftCameraSocket",
            "socket number",
        ),
        (lambda d: d["cameraData"][1][1].__setitem__("width", 0), r"cameraData\[1\]\.width/height", "positive"),
    ],
)
def test_depthai_json_with_wrongly_typed_fields_names_the_key(
    oak_json: Path, tmp_path: Path, edit, key: str, expected: str
) -> None:
    data = json.loads(oak_json.read_text())
    data["cameraData"].sort(key=lambda item: item[0])  # sockets 0 (A), 1 (B), 2 (C)
    edit(data)
    broken = tmp_path / "typed.json"
    broken.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=rf"typed\.json: {key}: .*\(expected .*{expected}"):
        from_depthai_json(broken, size=(640, 400))


def test_opencv_file_with_text_where_a_matrix_belongs_names_the_key(zed_hd: StereoCalibration, tmp_path: Path) -> None:
    path = tmp_path / "text.json"
    path.write_text(
        json.dumps(
            {
                "K1": "see datasheet",
                "D1": [0] * 5,
                "K2": zed_hd.K2.tolist(),
                "D2": [0] * 5,
                "R": {"yaw": 0},
                "T": [-0.06, 0, 0],
                "image_width": 1280,
                "image_height": 720,
            }
        )
    )
    with pytest.raises(CalibrationError, match=r"text\.json: K1: is not a matrix or a list of numbers \(expected 9"):
        from_opencv_file(path)
    path.write_text(path.read_text().replace('"see datasheet"', json.dumps(zed_hd.K1.tolist())))
    with pytest.raises(CalibrationError, match=r"text\.json: R: is not a matrix or a list of numbers"):
        from_opencv_file(path)


# ---------------------------------------------------------------- KITTI and rectified-only


def test_kitti_real_file_gives_p_rect_focal_and_baseline(kitti_file: Path) -> None:
    calib = from_kitti(kitti_file)
    assert calib.is_rectified
    assert calib.K1[0, 0] == pytest.approx(721.5377)
    assert calib.baseline_m == pytest.approx(0.5327, abs=2e-4)
    assert calib.image_size == (1242, 375)
    assert load_calibration(kitti_file) == calib


def test_kitti_missing_camera_and_swapped_pair(kitti_file: Path) -> None:
    with pytest.raises(CalibrationError, match=r"P_rect_05: key is missing"):
        from_kitti(kitti_file, "02", "05")
    with pytest.raises(CalibrationError, match="swap"):
        from_kitti(kitti_file, "03", "02")


def test_from_rectified_checks_values() -> None:
    calib = from_rectified(700.0, 640.0, 360.0, 0.063, (1280, 720))
    assert calib.is_rectified and calib.baseline_m == pytest.approx(0.063)
    with pytest.raises(CalibrationError, match="baseline_m"):
        from_rectified(700.0, 640.0, 360.0, -0.063, (1280, 720))
    with pytest.raises(CalibrationError, match="focal_px.*finite"):
        from_rectified(float("inf"), 640.0, 360.0, 0.063, (1280, 720))


def test_calibration_rejects_non_rotation_and_bad_distortion() -> None:
    k = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    with pytest.raises(CalibrationError, match="R: is not a rotation"):
        StereoCalibration(k, np.zeros(5), k, np.zeros(5), 2 * np.eye(3), np.array([-0.1, 0, 0]), (640, 480))
    with pytest.raises(CalibrationError, match="D2: has 3 coefficients"):
        StereoCalibration(k, np.zeros(5), k, np.zeros(3), np.eye(3), np.array([-0.1, 0, 0]), (640, 480))


# ---------------------------------------------------------------- dispatch on content


def test_load_calibration_dispatches_on_content(
    zed_dir: Path, kitti_file: Path, zed_hd: StereoCalibration, tmp_path: Path
) -> None:
    renamed = tmp_path / "factory.txt"
    renamed.write_bytes((zed_dir / "SN14966.conf").read_bytes())
    assert detect_format(renamed) == "zed"
    assert load_calibration(renamed, "HD") == zed_hd
    assert detect_format(kitti_file) == "kitti"
    yaml_path = write_opencv_file(zed_hd, tmp_path / "c.yml")
    assert load_calibration(yaml_path) == zed_hd
    with pytest.raises(CalibrationError, match="resolution"):
        load_calibration(renamed)
    unknown = tmp_path / "notes.txt"
    unknown.write_text("hello: world\n")
    with pytest.raises(CalibrationError, match="no known calibration format"):
        load_calibration(unknown)


def test_calibration_with_a_malformed_image_size_names_it() -> None:
    k = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    with pytest.raises(CalibrationError, match=r"image_size: is \(640,\) \(expected \(width, height\) in pixels\)"):
        StereoCalibration(k, np.zeros(5), k, np.zeros(5), np.eye(3), np.array([-0.1, 0, 0]), (640,))


def test_truncated_opencv_xml_is_a_calibration_error_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "stereo.xml"
    path.write_text('<?xml version="1.0"?>\n<opencv_storage><K1 type_id="opencv-matrix"><rows>3</rows')
    with pytest.raises(CalibrationError, match=r"stereo\.xml: <file>: is not a valid FileStorage file"):
        load_calibration(path)
