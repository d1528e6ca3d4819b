"""stereo.metrics against hand-computed values (reference facts §6)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stereo.metrics import MetricAverager, NoValidPixelsError, image_metrics, valid_mask

# Valid ground truth 1, 2, 4, 10, 100; the second row's 0, NaN and 200 (≥ 192) do not count.
GT = np.array([[1.0, 2.0, 4.0, 10.0, 100.0], [0.0, np.nan, 200.0, 0.0, 0.0]], np.float32)
# Errors 0.5, 1, 4, 6, 4; ratios max(p/g, g/p) 1.5, 1.5, 2, 1.6, 1.04.
PRED = np.array([[1.5, 3.0, 8.0, 16.0, 104.0], [9.0, 9.0, 9.0, 9.0, 9.0]], np.float32)


def test_valid_mask_is_finite_and_strictly_inside_zero_to_max_disp() -> None:
    gt = np.array([0.0, -1.0, np.nan, np.inf, 191.9, 192.0, 1e-3], np.float32)
    assert valid_mask(gt).tolist() == [False, False, False, False, True, False, True]
    assert valid_mask(gt, max_disp=100).tolist() == [False, False, False, False, False, False, True]


def test_error_metrics_match_hand_computation() -> None:
    m = image_metrics(PRED, GT)
    assert m["valid_pixels"] == 5
    assert m["epe"] == pytest.approx(15.5 / 5)
    assert m["rmse"] == pytest.approx(math.sqrt((0.25 + 1 + 16 + 36 + 16) / 5))
    # D1: err > 3 and err/g > 5 %: 4/4 and 6/10 are, 4/100 is not.
    assert m["d1_all"] == pytest.approx(2 / 5)


def test_bad_n_thresholds_are_strict() -> None:
    m = image_metrics(PRED, GT)
    # err 0.5 is not > 0.5, err 1 is not > 1, err 4 is not > 4.
    assert (m["bad_0_5"], m["bad_1"], m["bad_2"], m["bad_3"], m["bad_4"], m["bad_5"]) == pytest.approx(
        (4 / 5, 3 / 5, 3 / 5, 3 / 5, 1 / 5, 1 / 5)
    )


def test_relative_metrics_are_on_disparity() -> None:
    m = image_metrics(PRED, GT)
    assert m["abs_rel"] == pytest.approx((0.5 / 1 + 1 / 2 + 4 / 4 + 6 / 10 + 4 / 100) / 5)
    assert m["sq_rel"] == pytest.approx((0.25 / 1 + 1 / 2 + 16 / 4 + 36 / 10 + 16 / 100) / 5)
    logs = [math.log(1.5), math.log(1.5), math.log(2.0), math.log(1.6), math.log(1.04)]
    assert m["rmse_log"] == pytest.approx(math.sqrt(sum(v * v for v in logs) / 5))
    # ratios 1.5, 1.5, 2, 1.6, 1.04 against 1.25, 1.5625, 1.953125
    assert (m["delta1"], m["delta2"], m["delta3"]) == pytest.approx((1 / 5, 3 / 5, 4 / 5))
    assert "abs_rel_depth" not in m


def test_depth_metrics_appear_with_focal_length_and_baseline() -> None:
    m = image_metrics(PRED, GT, focal_px=100.0, baseline_m=0.5)  # f·B = 50 px·m
    # |Zp − Zg| / Zg = |g/p − 1|
    assert m["abs_rel_depth"] == pytest.approx((1 / 3 + 1 / 3 + 1 / 2 + 3 / 8 + 1 / 26) / 5)
    assert m["abs_rel_depth"] != pytest.approx(m["abs_rel"])
    assert m["delta1_depth"] == pytest.approx(m["delta1"])
    depth_errors = [50 / 1.5 - 50, 25 - 50 / 3, 12.5 - 6.25, 5 - 50 / 16, 0.5 - 50 / 104]
    assert m["mae_depth_m"] == pytest.approx(sum(map(abs, depth_errors)) / 5)
    assert m["rmse_depth_m"] == pytest.approx(math.sqrt(sum(e * e for e in depth_errors) / 5))


def test_zero_prediction_is_clamped_in_logs_and_ratios() -> None:
    m = image_metrics(np.array([[0.0]], np.float32), np.array([[2.0]], np.float32))
    assert m["rmse_log"] == pytest.approx(math.log(2.0 / 1e-6))
    assert m["delta1"] == 0.0 and m["delta3"] == 0.0
    assert m["abs_rel"] == pytest.approx(1.0) and m["epe"] == pytest.approx(2.0)


def test_invalid_inputs_raise_specific_errors() -> None:
    with pytest.raises(NoValidPixelsError, match="no ground-truth pixel"):
        image_metrics(np.ones((2, 2), np.float32), np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match="same H×W shape"):
        image_metrics(np.ones((2, 2)), np.ones((2, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        image_metrics(np.full((1, 1), np.nan), np.ones((1, 1)))
    with pytest.raises(ValueError, match="both focal_px and baseline_m"):
        image_metrics(PRED, GT, focal_px=100.0)


def test_average_is_over_images_with_rmse_rooted_per_image() -> None:
    averager = MetricAverager()
    averager.update(np.array([[4.0]], np.float32), np.array([[1.0]], np.float32))  # err 3
    averager.update(np.array([[2.0, 9.0]], np.float32), np.array([[2.0, 5.0]], np.float32))  # err 0, 4
    assert averager.update(np.ones((1, 1), np.float32), np.zeros((1, 1), np.float32)) is None
    mean = averager.mean()
    assert (averager.count, averager.skipped) == (2, 1)
    assert mean["epe"] == pytest.approx((3 + 2) / 2)  # pixel-weighted would be 7/3
    assert mean["rmse"] == pytest.approx((3 + math.sqrt(8)) / 2)  # pooled would be sqrt(25/3)
    assert mean["bad_3"] == pytest.approx((0 + 0.5) / 2)


def test_empty_averager_and_mismatched_keys_raise() -> None:
    averager = MetricAverager()
    with pytest.raises(NoValidPixelsError, match="no image"):
        averager.mean()
    averager.add({"epe": 1.0})
    with pytest.raises(ValueError, match="differ"):
        averager.add({"rmse": 1.0})
