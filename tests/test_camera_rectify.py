"""Rectification: sign conventions, and the truth test on a scene rendered through a distorted, rotated rig."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from camera import FrameSizeError, Rectifier, StereoCalibration, from_kitti, from_rectified, from_zed_conf
from camera.zed_conf import parse_ini
from stereo.pinhole import depth_from_disparity

WIDTH, HEIGHT = 640, 400


# ---------------------------------------------------------------- a scene rendered through a known rig


def _rig() -> StereoCalibration:
    """A ZED-Mini-like rig with real-looking distortion, a small rotation and a slightly skewed baseline."""
    k1 = np.array([[420.0, 0, 322.5], [0, 421.0, 197.0], [0, 0, 1]])
    k2 = np.array([[424.0, 0, 315.0], [0, 423.5, 206.0], [0, 0, 1]])
    d1 = np.array([-0.17, 0.026, 0.0005, -0.0003, 0.0])
    d2 = np.array([-0.16, 0.024, -0.0004, 0.0002, 0.0])
    rotation = cv2.Rodrigues(np.array([0.006, -0.012, 0.004]))[0]
    translation = np.array([-0.063, 0.0012, -0.0008])
    return StereoCalibration(k1, d1, k2, d2, rotation, translation, (WIDTH, HEIGHT), source="test rig")


#: The textured plane: a point on it, its normal and two in-plane axes (world = raw left camera frame).
PLANE_POINT = np.array([0.0, 0.0, 1.4])
PLANE_NORMAL = np.array([0.25, -0.1, -1.0]) / np.linalg.norm([0.25, -0.1, -1.0])
AXIS_U = np.cross([0.0, 1.0, 0.0], PLANE_NORMAL)
AXIS_U /= np.linalg.norm(AXIS_U)
AXIS_V = np.cross(PLANE_NORMAL, AXIS_U)
DOT_SIGMA_M = 0.007
#: In-plane (u, v) positions of dark marker dots, metres.
DOTS_UV = np.array([[u, v] for u in (-0.45, -0.15, 0.15, 0.45) for v in (-0.25, 0.0, 0.25)])
TEXTURE_SIZE_M = 3.0


CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12)


def _undistort(
    points: np.ndarray, k: np.ndarray, d: np.ndarray, r: np.ndarray | None = None, p: np.ndarray | None = None
) -> np.ndarray:
    """Raw pixel positions (N, 2) → normalised rays, or rectified pixels when r and p are given (N, 2)."""
    kwargs = {} if r is None else {"R": r, "P": p}
    return cv2.undistortPoints(points.reshape(-1, 1, 2), k, d, criteria=CRITERIA, **kwargs).reshape(-1, 2)


def _texture() -> np.ndarray:
    rng = np.random.default_rng(7)
    noise = cv2.GaussianBlur(rng.uniform(0, 1, (1024, 1024)).astype(np.float32), (0, 0), 4)
    noise = (noise - noise.mean()) / noise.std()
    return (150 + 14 * noise).astype(np.float32)


def _render(calib: StereoCalibration, right: bool, texture: np.ndarray) -> np.ndarray:
    """An RGB uint8 image of the plane as seen by one raw (distorted) camera of `calib`."""
    k, d = (calib.K2, calib.D2) if right else (calib.K1, calib.D1)
    rotation, translation = (calib.R, calib.T) if right else (np.eye(3), np.zeros(3))
    u, v = np.meshgrid(np.arange(WIDTH, dtype=np.float64), np.arange(HEIGHT, dtype=np.float64))
    rays_cam = _undistort(np.stack([u.ravel(), v.ravel()], axis=1), k, d)
    rays = np.hstack([rays_cam, np.ones((len(rays_cam), 1))]) @ rotation  # camera → world: Rᵀ·ray
    centre = -rotation.T @ translation
    s = ((PLANE_POINT - centre) @ PLANE_NORMAL) / (rays @ PLANE_NORMAL)
    hits = centre + s[:, None] * rays - PLANE_POINT
    plane_u, plane_v = hits @ AXIS_U, hits @ AXIS_V
    scale = texture.shape[0] / TEXTURE_SIZE_M
    map_x = ((plane_u + TEXTURE_SIZE_M / 2) * scale).astype(np.float32).reshape(HEIGHT, WIDTH)
    map_y = ((plane_v + TEXTURE_SIZE_M / 2) * scale).astype(np.float32).reshape(HEIGHT, WIDTH)
    grey = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR).ravel()
    for du, dv in DOTS_UV:  # markers: a white sticker with a dark Gaussian dot, on the textured plane
        r2 = ((plane_u - du) ** 2 + (plane_v - dv) ** 2) / DOT_SIGMA_M**2
        sticker = np.clip(5.0 - np.sqrt(r2), 0.0, 1.0)
        grey = grey * (1.0 - sticker) + 200.0 * sticker - 150.0 * np.exp(-r2 / 2)
    image = np.clip(grey, 0, 255).reshape(HEIGHT, WIDTH).astype(np.uint8)
    return np.repeat(image[:, :, None], 3, axis=2)


def _dot_world_points() -> np.ndarray:
    return PLANE_POINT + DOTS_UV[:, :1] * AXIS_U + DOTS_UV[:, 1:] * AXIS_V


def _centroid(image: np.ndarray, guess: np.ndarray, radius: int = 9) -> np.ndarray:
    """Sub-pixel centre of the dark dot near `guess` (x, y): darkness-weighted mean over a window."""
    x0, y0 = int(round(guess[0])), int(round(guess[1]))
    window = image[y0 - radius : y0 + radius + 1, x0 - radius : x0 + radius + 1, 0].astype(np.float64)
    weight = np.clip(110.0 - window, 0, None)  # only the dot: sticker 200, texture 150 ± 14, dot centre 50
    ys, xs = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    return np.array([x0 + (weight * xs).sum() / weight.sum(), y0 + (weight * ys).sum() / weight.sum()])


@pytest.fixture(scope="module")
def rendered() -> tuple[StereoCalibration, np.ndarray, np.ndarray]:
    calib = _rig()
    texture = _texture()
    return calib, _render(calib, False, texture), _render(calib, True, texture)


def test_rectified_rig_puts_points_on_one_row_and_gives_true_depth(rendered) -> None:
    calib, raw_left, raw_right = rendered
    rectifier = Rectifier(calib)
    left, right = rectifier.rectify(raw_left, raw_right)
    assert left.shape == raw_left.shape and left.dtype == np.uint8
    points = _dot_world_points()
    in_rectified_left = np.hstack([points @ rectifier.R1.T, np.ones((len(points), 1))])  # P1, P2 act on these
    guess_left = in_rectified_left @ rectifier.P1.T
    guess_right = in_rectified_left @ rectifier.P2.T
    vertical, depth_error, disparities = [], [], []
    for point, gl, gr in zip(points, guess_left, guess_right):
        found_left = _centroid(left, gl[:2] / gl[2])
        found_right = _centroid(right, gr[:2] / gr[2])
        assert np.linalg.norm(found_left - gl[:2] / gl[2]) < 0.2  # the image follows the model
        disparity = found_left[0] - found_right[0]
        depth_true = (rectifier.R1 @ point)[2]
        vertical.append(abs(found_left[1] - found_right[1]))
        depth_error.append(
            abs(float(depth_from_disparity(disparity, rectifier.focal_px, rectifier.baseline_m)) - depth_true)
            / depth_true
        )
        disparities.append(disparity)
    # the raw images really are misaligned: without rectification rows differ by pixels
    raw_rows = [
        abs(_centroid(raw_left, g)[1] - _centroid(raw_right, h)[1])
        for g, h in zip(
            cv2.projectPoints(points, np.zeros(3), np.zeros(3), calib.K1, calib.D1)[0].reshape(-1, 2),
            cv2.projectPoints(points, cv2.Rodrigues(calib.R)[0], calib.T, calib.K2, calib.D2)[0].reshape(-1, 2),
        )
    ]
    assert max(raw_rows) > 5.0
    assert max(vertical) < 0.5, vertical
    assert max(depth_error) < 0.01, depth_error
    assert min(disparities) > 0


def test_rectifier_sign_convention_p2_and_q(rendered) -> None:
    calib, _, _ = rendered
    rectifier = Rectifier(calib)
    assert abs(rectifier.P2[0, 3] / rectifier.P2[0, 0]) == pytest.approx(rectifier.baseline_m, rel=1e-12)
    assert rectifier.baseline_m == pytest.approx(calib.baseline_m, rel=1e-9)
    assert rectifier.P2[0, 3] < 0
    point = np.array([0.1, -0.05, 2.0])
    x_left = rectifier.P1 @ np.append(rectifier.R1 @ point, 1.0)
    x_right = rectifier.P2 @ np.append(rectifier.R1 @ point, 1.0)
    # the same pixel through the right camera's own rectified frame (R2 after the raw extrinsics)
    in_right = rectifier.R2 @ (calib.R @ point + calib.T)
    np.testing.assert_allclose(x_right, rectifier.P2[:, :3] @ in_right, rtol=1e-9)
    x_left, x_right = x_left[:2] / x_left[2], x_right[:2] / x_right[2]
    disparity = x_left[0] - x_right[0]
    assert disparity > 0
    assert x_left[1] == pytest.approx(x_right[1], abs=1e-9)
    homogeneous = rectifier.Q @ np.array([x_left[0], x_left[1], disparity, 1.0])
    np.testing.assert_allclose(homogeneous[:3] / homogeneous[3], rectifier.R1 @ point, rtol=1e-9)


@pytest.mark.parametrize("serial", ["SN1010", "SN14966", "SN1499"])
def test_real_zed_calibration_rectifies_to_its_baseline_with_aligned_rows(shared_data: Path, serial: str) -> None:
    calib = from_zed_conf(shared_data / "calibration" / "zed" / f"{serial}.conf", "HD")
    rectifier = Rectifier(calib)
    assert rectifier.size == (1280, 720)
    assert rectifier.baseline_m == pytest.approx(calib.baseline_m, rel=1e-9)
    assert 600 < rectifier.focal_px < 800
    cx, cy = rectifier.principal_point
    assert 0 < cx < 1280 and 0 < cy < 720
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(-0.6, 0.6, 30), rng.uniform(-0.3, 0.3, 30), rng.uniform(1.0, 4.0, 30)])
    raw_left = cv2.projectPoints(points, np.zeros(3), np.zeros(3), calib.K1, calib.D1)[0]
    raw_right = cv2.projectPoints(points, cv2.Rodrigues(calib.R)[0], calib.T, calib.K2, calib.D2)[0]
    rect_left = _undistort(raw_left, calib.K1, calib.D1, rectifier.R1, rectifier.P1)
    rect_right = _undistort(raw_right, calib.K2, calib.D2, rectifier.R2, rectifier.P2)
    np.testing.assert_allclose(rect_left[:, 1], rect_right[:, 1], atol=0.01)
    depth = depth_from_disparity(rect_left[:, 0] - rect_right[:, 0], rectifier.focal_px, rectifier.baseline_m)
    np.testing.assert_allclose(depth, (points @ rectifier.R1.T)[:, 2], rtol=1e-4)


@pytest.mark.parametrize("serial", ["SN1010", "SN14966", "SN1499"])
def test_zed_rectification_is_stereolabs_samples_with_opencvs_sign_of_t(shared_data: Path, serial: str) -> None:
    """Stereolabs' OpenCV sample feeds stereoRectify R = Rodrigues([RX, CV, RZ]) and T = +[Baseline, TY, TZ] mm.

    We keep its R and store T with OpenCV's sign (metres): the rectifying rotations and projections
    must be the sample's, except that P2[0,3] flips to negative (right camera on the +x side).
    """
    path = shared_data / "calibration" / "zed" / f"{serial}.conf"
    calib = from_zed_conf(path, "HD")
    stereo = parse_ini(path.read_bytes().decode("utf-8-sig"), path)["STEREO"]
    vector = np.array([float(stereo[f"{axis}_hd"]) for axis in ("rx", "cv", "rz")])
    t_mm = np.array([float(stereo["baseline"]), float(stereo.get("ty_hd", 0.0)), float(stereo.get("tz_hd", 0.0))])
    r1, r2, p1, p2, _, _, _ = cv2.stereoRectify(
        calib.K1,
        calib.D1,
        calib.K2,
        calib.D2,
        (1280, 720),
        cv2.Rodrigues(vector)[0],
        t_mm.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=0.0,
        newImageSize=(1280, 720),
    )
    ours = Rectifier(calib)
    np.testing.assert_allclose(ours.R1, r1, atol=1e-12)
    np.testing.assert_allclose(ours.R2, r2, atol=1e-12)
    np.testing.assert_allclose(ours.P1, p1, atol=1e-9)
    np.testing.assert_allclose(ours.P2[:, :3], p2[:, :3], atol=1e-9)
    assert p2[0, 3] > 0 > ours.P2[0, 3]
    assert ours.P2[0, 3] == pytest.approx(-p2[0, 3] / 1000.0, rel=1e-9)
    assert abs(ours.P2[0, 3] / ours.P2[0, 0]) == pytest.approx(np.linalg.norm(t_mm) / 1000.0, rel=1e-9)


def test_frame_of_wrong_size_is_rejected_with_expected_size(rendered) -> None:
    calib, left, right = rendered
    rectifier = Rectifier(calib)
    with pytest.raises(FrameSizeError, match=r"right frame: is 320×200 px .*640×400 px"):
        rectifier.rectify(left, right[::2, ::2])
    with pytest.raises(FrameSizeError, match="H×W×3 uint8"):
        rectifier.rectify(left[:, :, 0], right)


def test_rectified_calibration_passes_pixels_through(shared_data: Path) -> None:
    rectifier = Rectifier(from_kitti(shared_data / "calibration" / "kitti" / "2011_09_26_calib_cam_to_cam.txt"))
    left = np.random.default_rng(0).integers(0, 255, (375, 1242, 3), dtype=np.uint8)
    out_left, out_right = rectifier.rectify(left, left)
    assert np.array_equal(out_left, left)
    assert rectifier.focal_px == pytest.approx(721.5377)
    assert rectifier.baseline_m == pytest.approx(0.5327, abs=2e-4)
    assert rectifier.P2[0, 3] < 0


def test_rectified_q_matches_opencv_for_a_distortion_free_rig() -> None:
    calib = from_rectified(500.0, 320.0, 240.0, 0.1, (640, 480))
    ours = Rectifier(calib)
    *_, p2, q, _, _ = cv2.stereoRectify(
        calib.K1,
        calib.D1,
        calib.K2,
        calib.D2,
        (640, 480),
        calib.R,
        calib.T.reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=-1,
    )
    np.testing.assert_allclose(ours.P2, p2, atol=1e-9)
    np.testing.assert_allclose(ours.Q, q, atol=1e-9)


def test_rectify_maps_are_built_once_and_reused(rendered, monkeypatch: pytest.MonkeyPatch) -> None:
    calib, left, right = rendered
    calls: list[int] = []
    original = cv2.initUndistortRectifyMap

    def counting(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(cv2, "initUndistortRectifyMap", counting)
    rectifier = Rectifier(calib)
    first = rectifier.rectify(left, right)
    second = rectifier.rectify(left, right)
    assert len(calls) == 2  # one map per view, at construction
    assert np.array_equal(first[0], second[0]) and not np.array_equal(first[0], left)


def test_label_maps_are_built_once_and_move_ids_like_the_image(rendered, monkeypatch: pytest.MonkeyPatch) -> None:
    calib, left, right = rendered
    labels = np.zeros((HEIGHT, WIDTH), np.uint16)
    labels[100:180, 200:420] = 7
    labels[250:300, 50:150] = 65535  # the trunk id survives (exact in float32)
    calls: list[int] = []
    original = cv2.initUndistortRectifyMap

    def counting(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    rectifier = Rectifier(calib)
    monkeypatch.setattr(cv2, "initUndistortRectifyMap", counting)
    first, second = rectifier.rectify_labels(labels), rectifier.rectify_labels(labels)
    assert len(calls) == 1  # the label tables, once; the image tables were built before
    assert first.dtype == np.int32 and np.array_equal(first, second)
    assert set(np.unique(first)) == {0, 7, 65535}  # nearest id: no blends between ids
    moved = rectifier.rectify(np.repeat((labels == 7).astype(np.uint8)[:, :, None] * 255, 3, axis=2), right)[0][..., 0]
    agree = (first == 7) == (moved > 127)
    assert agree.mean() > 0.995  # the labels land where the image's pixels land
    assert not np.array_equal(first, labels.astype(np.int32))  # a real rig: something moved
