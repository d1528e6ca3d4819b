"""Training transforms: valid-preferring crop, asymmetric colour jitter, normalisation, seeded augmentation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stereo.datasets.transforms import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    AsymmetricColorJitter,
    Augmented,
    TrainTransform,
    normalize_image,
    random_valid_crop,
)


def _sample(height=64, width=96, seed=0):
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    return {
        "left": image,
        "right": image.copy(),
        "disparity": np.zeros((height, width), np.float32),
        "meta": {"name": "x"},
    }


def test_crop_prefers_the_window_with_valid_disparity():
    sample = _sample(200, 200)
    sample["disparity"][150:, 150:] = 10.0  # valid only in the bottom-right corner
    sample["disparity"][:20, :20] = 500.0  # beyond max_disp: not valid
    counts = []
    for seed in range(20):
        out = random_valid_crop(sample, 64, 64, np.random.default_rng(seed), enough_valid=4096)
        counts.append(int(np.count_nonzero((out["disparity"] > 0) & (out["disparity"] < 192))))
        assert out["left"].shape == (64, 64, 3) and out["disparity"].shape == (64, 64)
    # A single uniform draw lands on the corner with probability ≈ 0.2; the best of 20 nearly always does.
    assert np.mean([c > 0 for c in counts]) >= 0.9


def test_crop_stops_at_enough_valid_pixels_and_keeps_images_aligned():
    sample = _sample(100, 120)
    sample["disparity"][:] = np.arange(120, dtype=np.float32)[None, :] % 50 + 1
    out = random_valid_crop(sample, 32, 64, np.random.default_rng(3))
    col = int(out["disparity"][0, 0] - 1)
    rows = np.where((sample["left"] == out["left"][0, 0]).all(axis=-1))
    assert out["left"].shape == (32, 64, 3)
    assert np.array_equal(out["left"], out["right"])
    assert any(c % 50 == col for c in rows[1])


def test_crop_larger_than_the_image_returns_it_uncropped():
    sample = _sample(40, 50)
    assert random_valid_crop(sample, 64, 64, np.random.default_rng(0)) is sample


def test_jitter_is_joint_with_probability_point_eight_else_per_view():
    jitter = AsymmetricColorJitter()
    sample = _sample(8, 8)
    differing = 0
    for seed in range(400):
        out = jitter(sample, np.random.default_rng(seed))
        differing += not np.array_equal(out["left"], out["right"])
    assert 0.14 < differing / 400 < 0.26
    assert np.array_equal(out["disparity"], sample["disparity"])


def test_jitter_with_zero_strength_is_the_identity():
    jitter = AsymmetricColorJitter(0.0, 0.0, 0.0, 0.0)
    sample = _sample(16, 16)
    out = jitter(sample, np.random.default_rng(1))
    np.testing.assert_allclose(out["left"].astype(int), sample["left"].astype(int), atol=1)


def test_brightness_only_scales_pixel_values():
    jitter = AsymmetricColorJitter(0.4, 0.0, 0.0, 0.0, asymmetric_prob=0.0)
    sample = _sample(16, 16)
    sample["left"] = sample["right"] = np.full((16, 16, 3), 100, np.uint8)
    out = jitter(sample, np.random.default_rng(5))
    value = int(out["left"][0, 0, 0])
    assert 60 <= value <= 140 and value != 100 and np.all(out["left"] == value)


def test_normalisation_uses_imagenet_statistics():
    image = np.zeros((2, 3, 3), np.uint8)
    image[..., 0] = 255
    tensor = normalize_image(image)
    assert tensor.shape == (3, 2, 3) and tensor.dtype == torch.float32
    assert tensor[0, 0, 0].item() == pytest.approx((1 - IMAGENET_MEAN[0]) / IMAGENET_STD[0], rel=1e-6)
    assert tensor[1, 0, 0].item() == pytest.approx(-IMAGENET_MEAN[1] / IMAGENET_STD[1], rel=1e-6)


def test_augmentation_depends_only_on_seed_epoch_and_index():
    raw = [_sample(80, 100, seed=i) for i in range(2)]
    for s in raw:
        s["disparity"][:] = 5.0
    transform = TrainTransform(32, 64, max_disp=192.0)
    a, b = Augmented(raw, transform, seed=7), Augmented(raw, transform, seed=7)
    torch.testing.assert_close(a[1]["left"], b[1]["left"])
    first = a[1]["left"].clone()
    a.set_epoch(1)
    assert not torch.equal(a[1]["left"], first)
    assert a[1]["left"].shape == (3, 32, 64) and a[1]["disparity"].shape == (32, 64)
