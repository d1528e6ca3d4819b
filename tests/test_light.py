"""Changed light for the segmenter benchmark: each change does what its name says, repeatably."""

from __future__ import annotations

import numpy as np
import pytest

from branchrange.learning.light_changes import LIGHT_CHANGES, changed_light


@pytest.fixture
def image():
    rng = np.random.default_rng(3)
    base = rng.integers(40, 200, size=(60, 80, 3)).astype(np.uint8)
    base[:10] = 250  # a bright sky band
    return base


def test_each_change_of_light_does_what_its_name_says(image):
    rng = np.random.default_rng(0)
    out = {name: changed_light(image, name, rng) for name in LIGHT_CHANGES}
    assert all(o.dtype == np.uint8 and o.shape == image.shape for o in out.values())
    mean = image.astype(float).mean()
    assert out["dusk"].mean() == pytest.approx(0.3 * mean, rel=0.05)
    assert (out["glare"][:10] == 255).all() and out["glare"].mean() > 1.4 * mean  # brighter, the sky clipped
    assert out["haze"].std() == pytest.approx(0.45 * image.std(), rel=0.05) and out["haze"].min() >= 112
    red, blue = (out["warm"][..., k].astype(float).mean() / image[..., k].mean() for k in (0, 2))
    assert red > 1.15 and blue == pytest.approx(0.7, abs=0.01)
    noise = out["high_gain"][10:].astype(float) - image[10:]
    assert abs(noise.mean()) < 0.3 and noise.std() == pytest.approx(6.0, rel=0.1)


def test_a_change_of_light_repeats_with_its_seed_and_names_the_known_ones(image):
    first = changed_light(image, "high_gain", np.random.default_rng(7))
    assert np.array_equal(first, changed_light(image, "high_gain", np.random.default_rng(7)))
    assert not np.array_equal(first, changed_light(image, "high_gain", np.random.default_rng(8)))
    with pytest.raises(ValueError, match="unknown light change 'night'.*dusk, glare, haze, warm, high_gain"):
        changed_light(image, "night", np.random.default_rng(0))
