"""Windowed disparity (`compute_roi`): SGBM against its whole frame, EMCStereo against a hand-made crop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stereo import EMCStereo
from stereo.backends import BackendConfigError, SGBMBackend, StereoInputError
from stereo.backends.emcstereo import IMAGENET_MEAN, IMAGENET_STD, EMCStereoBackend
from stereo.padding import compute_padding
from stereo.synth import SynthCamera, render_scene
from stereo.synth.render import SyntheticScene

SGBM_RANGE = 64


@pytest.fixture(scope="module")
def scene() -> SyntheticScene:
    """A 240×160 synthetic tree (f = 400 px, B = 0.063 m: true disparities ≈ 2–31 px), rendered in < 1 s."""
    return render_scene(1, SynthCamera(240, 160, 400.0, 0.063))


@pytest.fixture(scope="module")
def sgbm() -> SGBMBackend:
    """The default: the left-right check in regions too, so a region is post-processed exactly as the whole frame."""
    return SGBMBackend(max_disp=SGBM_RANGE)


def window_around_truth(scene: SyntheticScene, roi: tuple[int, int, int, int]) -> tuple[int, int]:
    """(d_min, d_range) covering the 2nd–98th percentile of the box's true disparity with 4 px to spare."""
    x0, y0, x1, y1 = roi
    truth = scene.disparity[y0:y1, x0:x1]
    low, high = np.percentile(truth[truth > 0], [2, 98])
    d_min = max(int(low) - 4, 0)
    return d_min, int(np.ceil(high)) + 4 - d_min


# An interior box, one on the top-left corner (its search columns lie left of the frame: replicated,
# as the whole frame pads) and one on the bottom-right corner (context clipped by the frame).
ROIS = [(60, 40, 180, 120), (0, 0, 100, 80), (140, 80, 240, 160)]


@pytest.mark.parametrize("roi", ROIS)
def test_sgbm_roi_with_the_truth_in_its_window_equals_the_whole_frame_inside_the_box(
    scene: SyntheticScene, sgbm: SGBMBackend, roi: tuple[int, int, int, int]
) -> None:
    # Tolerance: the SGM paths start at the crop's edge (16 px of context) instead of the frame's,
    # and the uniqueness and speckle filters see a narrower range, so a few pixels may differ.
    # Measured: 99.7–100 % of pixels valid in both agree within 0.5 px; the valid sets differ by ≤ 0.6 %.
    x0, y0, x1, y1 = roi
    d_min, d_range = window_around_truth(scene, roi)
    whole = sgbm.compute(scene.left, scene.right).disparity[y0:y1, x0:x1]
    window = sgbm.compute_roi(scene.left, scene.right, roi, d_min, d_range)
    assert window.disparity.shape == window.confidence.shape == (y1 - y0, x1 - x0)
    assert window.disparity.dtype == np.float32 and window.confidence.dtype == np.float32
    assert (window.backend, window.max_disparity) == ("sgbm", d_min + d_range)
    valid, whole_valid = window.disparity > 0, whole > 0
    both = valid & whole_valid
    assert valid.mean() > 0.6 and both.sum() >= 0.95 * max(valid.sum(), whole_valid.sum())
    assert (np.abs(window.disparity - whole)[both] <= 0.5).mean() >= 0.98
    assert (window.disparity[valid] > d_min).all() and (window.disparity[valid] < d_min + d_range).all()
    assert (
        (window.confidence[~valid] == 0).all() and (window.confidence[valid] > 0).all() and window.confidence.max() <= 1
    )
    assert {"match", "total"} <= set(window.timing_ms)


def test_sgbm_roi_window_that_excludes_the_truth_is_mostly_invalid(scene: SyntheticScene, sgbm: SGBMBackend) -> None:
    roi = ROIS[0]
    x0, y0, x1, y1 = roi
    truth = scene.disparity[y0:y1, x0:x1]
    low, high = np.percentile(truth[truth > 0], [2, 98])
    nearer = sgbm.compute_roi(scene.left, scene.right, roi, int(np.ceil(high)) + 6, 16)  # looks for nearer surfaces
    farther = sgbm.compute_roi(scene.left, scene.right, roi, max(int(low) - 20, 0), 12)  # looks for farther ones
    # measured: 20 % valid looking nearer (repeated texture still matches somewhere), 0.8 % looking farther;
    # with the truth in the window 92 %.
    assert (nearer.disparity > 0).mean() < 0.35
    assert (farther.disparity > 0).mean() < 0.1


def test_sgbm_roi_range_not_a_multiple_of_16_stays_inside_the_requested_window(
    scene: SyntheticScene, sgbm: SGBMBackend
) -> None:
    result = sgbm.compute_roi(scene.left, scene.right, ROIS[0], 20, 10)  # OpenCV searches 16 from 20
    valid = result.disparity[result.disparity > 0]
    assert result.max_disparity == 30 and valid.size > 0
    assert valid.min() > 20 and valid.max() < 30


# ---------------------------------------------------------------- argument checks
@pytest.mark.parametrize(
    ("roi", "d_min", "d_range", "error", "message"),
    [
        ((0, 0, 241, 10), 0, 16, StereoInputError, r"roi \(0, 0, 241, 10\).*inside the 240×160 frame"),
        ((10, 10, 10, 20), 0, 16, StereoInputError, r"roi \(10, 10, 10, 20\) must be a non-empty box"),
        ((-1, 0, 10, 10), 0, 16, StereoInputError, r"roi \(-1, 0, 10, 10\)"),
        ((0, 0, 10), 0, 16, StereoInputError, r"four integers .*\(0, 0, 10\)"),
        ((0.5, 0, 10, 10), 0, 16, StereoInputError, "four integers"),
        ((0, 0, 10, 10), -1, 16, BackendConfigError, "d_min must be ≥ 0 px.*got -1"),
        ((0, 0, 10, 10), 0, 0, BackendConfigError, "d_range must be > 0 px, got 0"),
        ((0, 0, 10, 10), 2.5, 16, BackendConfigError, "d_min must be an integer.*2.5"),
    ],
)
def test_roi_arguments_are_checked_with_named_errors(
    scene: SyntheticScene, sgbm: SGBMBackend, roi: tuple, d_min: object, d_range: object, error: type, message: str
) -> None:
    with pytest.raises(error, match=message):
        sgbm.compute_roi(scene.left, scene.right, roi, d_min, d_range)


def test_roi_refuses_a_malformed_pair(scene: SyntheticScene, sgbm: SGBMBackend) -> None:
    with pytest.raises(StereoInputError, match="same shape"):
        sgbm.compute_roi(scene.left, scene.right[:, :-1], (0, 0, 10, 10), 0, 16)


# ---------------------------------------------------------------- EMCStereo
EMC_ROI = (64, 40, 120, 80)  # a 56×40 px box


@pytest.fixture(scope="module")
def emc() -> EMCStereoBackend:
    torch.manual_seed(0)
    return EMCStereoBackend(EMCStereo(), max_disp=192)


def network_on_crop(
    backend: EMCStereoBackend, left: np.ndarray, right: np.ndarray, max_disp: int
) -> tuple[np.ndarray, np.ndarray]:
    """The reference: normalise by hand, edge-pad top/right to the network's size, infer, un-pad."""
    padding = compute_padding(*left.shape[:2])

    def prepare(image: np.ndarray) -> torch.Tensor:
        scaled = (image.astype(np.float32) / 255.0 - np.float32(IMAGENET_MEAN)) / np.float32(IMAGENET_STD)
        padded = np.pad(scaled, ((padding.top, 0), (0, padding.right), (0, 0)), mode="edge")
        return torch.from_numpy(padded.transpose(2, 0, 1).copy())[None]

    with torch.inference_mode():
        disparity, confidence = backend.model.infer(prepare(left), prepare(right), max_disp=max_disp)
    height, width = left.shape[:2]
    return disparity[0, padding.top :, :width].numpy(), confidence[0, padding.top :, :width].numpy()


def test_emcstereo_roi_equals_a_manual_crop_shift_and_network_call(
    scene: SyntheticScene, emc: EMCStereoBackend
) -> None:
    # A box near the left edge, so part of the extension lies left of the frame, with a window offset d_min > 0.
    roi, d_min, d_range = (4, 100, 60, 140), 12, 16
    x0, y0, x1, y1 = roi
    result = emc.compute_roi(scene.left, scene.right, roi, d_min, d_range)
    assert result.disparity.shape == result.confidence.shape == (y1 - y0, x1 - x0)
    assert (result.backend, result.max_disparity) == ("emcstereo", d_min + d_range)
    assert np.isfinite(result.disparity).all() and 0 <= result.confidence.min() and result.confidence.max() <= 1
    valid = result.confidence > 0
    assert (
        valid.any() and (result.disparity[valid] >= d_min).all() and (result.disparity[valid] < d_min + d_range).all()
    )
    # Reference: left box extended d_range columns leftwards, right image shifted left by d_min;
    # columns left of the frame replicate column 0 (x0 = 4 < d_range + d_min).
    left_cols = np.clip(np.arange(x0 - d_range, x1), 0, None)
    right_cols = np.clip(np.arange(x0 - d_range - d_min, x1 - d_min), 0, None)
    left_crop = np.ascontiguousarray(scene.left[y0:y1][:, left_cols])
    right_crop = np.ascontiguousarray(scene.right[y0:y1][:, right_cols])
    disparity, confidence = (m[:, d_range:] for m in network_on_crop(emc, left_crop, right_crop, d_range))
    np.testing.assert_allclose(result.disparity, disparity + d_min, atol=1e-4)
    np.testing.assert_allclose(result.confidence, confidence, atol=1e-5)
    # A 4-px window: the network still searches 16 (the smallest range its hourglass takes), and its
    # estimates here (random weights: 7.50 ± 0.001 px) lie beyond the window, so every pixel is invalid.
    assert float(disparity.min()) >= 4
    narrow = emc.compute_roi(scene.left, scene.right, roi, d_min, 4)
    assert narrow.max_disparity == d_min + 4
    assert (narrow.disparity == 0).all() and (narrow.confidence == 0).all()


def test_emcstereo_roi_refuses_a_range_beyond_the_model(scene: SyntheticScene, emc: EMCStereoBackend) -> None:
    with pytest.raises(BackendConfigError, match=r"d_range 193 needs a 208-disparity search.*\(0, 192\]"):
        emc.compute_roi(scene.left, scene.right, EMC_ROI, 0, 193)


def test_onnx_backend_refuses_windowed_disparity(scene: SyntheticScene) -> None:
    pytest.importorskip("onnxruntime", reason="onnxruntime (a dependency of branchrange) is not installed")
    from stereo.backends.onnx import OnnxBackend

    # The refusal reads only the graph's size and range; exporting a graph to get them takes ~25 s
    # (tests/test_onnx_export.py does that), so this instance carries just those attributes.
    backend = OnnxBackend.__new__(OnnxBackend)
    backend.height, backend.width, backend.max_disparity = 256, 256, 32
    with pytest.raises(BackendConfigError, match="cannot compute a window.*exported for one 256×256 input"):
        backend.compute_roi(scene.left, scene.right, EMC_ROI, 0, 16)


def test_regions_without_the_left_right_check_only_gain_pixels(scene: SyntheticScene) -> None:
    """A region without the check (`roi_lr_check=False`) keeps every pixel the checked one keeps, with the
    same disparity, and more (thin structure the half-resolution check deletes); its confidence is 1 or 0."""
    roi = (60, 40, 180, 120)
    d_min, d_range = window_around_truth(scene, roi)
    checked = SGBMBackend(max_disp=SGBM_RANGE).compute_roi(scene.left, scene.right, roi, d_min, d_range)
    default = SGBMBackend(max_disp=SGBM_RANGE, roi_lr_check=False).compute_roi(
        scene.left, scene.right, roi, d_min, d_range
    )
    kept = checked.disparity > 0
    assert np.all(default.disparity[kept] == checked.disparity[kept])
    assert (default.disparity > 0).sum() > kept.sum()
    assert np.all(default.confidence[default.disparity > 0] == 1.0) and np.all(
        default.confidence[default.disparity == 0] == 0
    )
