"""The measures of `benchmarks/cut_point_noise.py` on hand-made errors with known answers.

Why: the benchmark sets `[tracking] disparity_sigma_px`, `lateral_sigma_px` and `bias_share` (what the fused
tracks' σ claims); an error split wrongly or a bias share miscounted would set them wrong silently.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import cut_point_noise  # noqa: E402


def test_an_error_along_the_line_of_sight_is_disparity_px_and_across_it_lateral_px() -> None:
    f, b = 700.0, 0.063
    true_m = np.array([0.0, 0.0, 2.0])
    # 1 px of disparity at 2 m moves the depth by r² / (f·B)
    depth_m = 2.0**2 / (f * b)
    depth, lateral = cut_point_noise.observation_errors_px(true_m + [0, 0, depth_m], true_m, f, b)
    assert depth == pytest.approx(1.0) and np.allclose(lateral, 0.0)
    # 3 px across at 2 m is 3·r / f metres; with a noise scale k = s^α of 2 it is 1.5 px in σ's units
    across = np.array([3 * 2.0 / f, 0.0, 0.0])
    depth, lateral = cut_point_noise.observation_errors_px(true_m + across, true_m, f, b, noise_scale=2.0)
    assert depth == pytest.approx(0.0, abs=1e-9) and np.linalg.norm(lateral) == pytest.approx(1.5)
    # the line of sight is the true point's: off axis, an error along it is still all depth
    off_axis = np.array([1.0, -0.5, 2.0])
    los = off_axis / np.linalg.norm(off_axis)
    depth, lateral = cut_point_noise.observation_errors_px(off_axis + 0.01 * los, off_axis, f, b)
    assert depth > 0 and np.allclose(lateral, 0.0, atol=1e-9)


def test_the_bias_share_separates_what_views_of_one_spot_share_from_what_they_do_not() -> None:
    rng = np.random.default_rng(0)
    # per cut point a bias of σ 1 px shared by its 40 views, plus independent noise of σ 1 px: share 0.5
    groups = {i: list(rng.normal(0, 1, 3) + rng.normal(0, 1, (40, 3))) for i in range(300)}
    assert cut_point_noise.bias_share(groups) == pytest.approx(0.5, abs=0.06)
    independent = {i: list(rng.normal(0, 1, (40, 3))) for i in range(300)}
    assert cut_point_noise.bias_share(independent) == pytest.approx(0.0, abs=0.03)
    assert cut_point_noise.bias_share({0: [np.zeros(3)] * 5}) is None  # one cut point: nothing to compare


def test_one_sigma_is_the_68th_percentile_of_the_absolute_error() -> None:
    rng = np.random.default_rng(1)
    assert cut_point_noise.one_sigma(rng.normal(0, 0.7, 20000)) == pytest.approx(0.7, rel=0.03)
    assert cut_point_noise.one_sigma([]) is None


def test_errors_that_grow_as_the_root_of_the_disparity_scale_are_flat_in_sigmas_px() -> None:
    rng = np.random.default_rng(2)
    # full-resolution errors of σ 0.4 px at s = 1 and 0.8 px at s = 4: they grow as √s
    scales = np.array([1] * 4000 + [4] * 4000)
    full = rng.normal(0, 0.4, 8000) * np.sqrt(scales)
    lateral = rng.normal(0, 2.0, (8000, 2)) * np.sqrt(scales)[:, None]
    for exponent, flat in ((0.5, True), (1.0, False)):
        found = {
            "scales": scales.tolist(),
            "exponent": exponent,
            "depth_px": (full / scales**exponent).tolist(),
            "lateral_px": (lateral / (scales**exponent)[:, None]).ravel().tolist(),
        }
        rows = cut_point_noise.by_disparity_scale(found)
        assert rows["1"]["observations"] == rows["4"]["observations"] == 4000
        assert rows["4"]["disparity_sigma_full_px"] == pytest.approx(0.8, rel=0.05)
        same = rows["4"]["disparity_sigma_px"] == pytest.approx(rows["1"]["disparity_sigma_px"], rel=0.06)
        assert same == flat
        assert rows["4"]["lateral_sigma_full_px"] == pytest.approx(2 * rows["1"]["lateral_sigma_px"], rel=0.06)
