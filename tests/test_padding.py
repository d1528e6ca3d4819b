"""stereo.padding: top/right padding to multiples of 32 and at least 256, edge mode for images, zeros for disparity."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stereo.padding import compute_padding, pad_disparity, pad_image, unpad


@pytest.mark.parametrize(
    ("size", "top", "right"),
    [((1080, 1920), 8, 0), ((256, 512), 0, 0), ((300, 200), 20, 56), ((375, 1242), 9, 6), ((10, 700), 246, 4)],
)
def test_padding_reaches_multiples_of_32_and_at_least_256(size: tuple[int, int], top: int, right: int) -> None:
    pad = compute_padding(*size)
    assert (pad.top, pad.right) == (top, right)
    assert all(s % 32 == 0 and s >= 256 for s in pad.padded_shape)


def test_numpy_image_padding_replicates_top_and_right_edges() -> None:
    image = np.arange(3 * 5 * 7, dtype=np.float32).reshape(3, 5, 7)  # (C, H, W)
    pad = compute_padding(5, 7, multiple=4, minimum=0)  # → 8 × 8
    padded = pad_image(image, pad)
    expected = np.pad(image, ((0, 0), (3, 0), (0, 1)), mode="edge")
    np.testing.assert_array_equal(padded, expected)
    np.testing.assert_array_equal(unpad(padded, pad), image)


def test_torch_padding_matches_replicate_and_zero_modes() -> None:
    images = torch.randn(2, 3, 250, 300)
    disparity = torch.rand(2, 250, 300) * 10
    pad = compute_padding(250, 300)
    padded = pad_image(images, pad)
    assert padded.shape == (2, 3, 256, 320)
    torch.testing.assert_close(padded, torch.nn.functional.pad(images, (0, 20, 6, 0), mode="replicate"))
    padded_disp = pad_disparity(disparity, pad)
    assert padded_disp[:, :6].abs().sum() == 0 and padded_disp[:, :, 300:].abs().sum() == 0
    torch.testing.assert_close(unpad(padded_disp, pad), disparity)
    np.testing.assert_array_equal(pad_disparity(disparity.numpy(), pad), padded_disp.numpy())


def test_padding_rejects_wrong_sizes() -> None:
    pad = compute_padding(250, 300)
    with pytest.raises(ValueError, match="unpad expects"):
        unpad(torch.zeros(1, 250, 300), pad)
    with pytest.raises(ValueError, match="pad_image expects"):
        pad_image(np.zeros((3, 251, 300)), pad)
    with pytest.raises(ValueError, match="positive"):
        compute_padding(0, 10)
