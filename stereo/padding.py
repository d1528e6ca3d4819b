"""Padding network inputs to the sizes EMCStereo accepts, and removing it from predictions.

The authors pad the **top** and the **right** so that H and W become multiples of 32; images are
padded in edge-replicate mode, disparity with zeros, and predictions are cropped back as
`[top:, :W − right]` before any metric. H and W must also be ≥ 256 (the 64-px SPP pool at ¼
resolution), so smaller inputs are padded further. Functions here act on the last two axes of a
numpy array or torch tensor (`(..., H, W)`), so they serve `(B, 3, H, W)` images and `(B, H, W)`
disparities alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import torch

PAD_MULTIPLE = 32
PAD_MINIMUM = 256

ArrayT = TypeVar("ArrayT", np.ndarray, torch.Tensor)


@dataclass(frozen=True)
class Padding:
    """Rows added at the top and columns added at the right of an `height × width` input."""

    top: int
    right: int
    height: int
    width: int

    @property
    def padded_shape(self) -> tuple[int, int]:
        """(H, W) after padding."""
        return self.height + self.top, self.width + self.right


def _padded_length(length: int, multiple: int, minimum: int) -> int:
    """The smallest multiple of `multiple` that is ≥ both `length` and `minimum`."""
    target = max(length, minimum)
    return -(-target // multiple) * multiple


def compute_padding(height: int, width: int, multiple: int = PAD_MULTIPLE, minimum: int = PAD_MINIMUM) -> Padding:
    """The top/right padding that makes an `height × width` input a multiple of `multiple` and ≥ `minimum`."""
    if height <= 0 or width <= 0:
        raise ValueError(f"cannot pad an input of size {height}×{width}: both sides must be positive")
    if multiple <= 0 or minimum < 0:
        raise ValueError(f"multiple {multiple} must be positive and minimum {minimum} non-negative")
    return Padding(
        top=_padded_length(height, multiple, minimum) - height,
        right=_padded_length(width, multiple, minimum) - width,
        height=height,
        width=width,
    )


def _check_size(x: ArrayT, padding: Padding, expected: tuple[int, int], what: str) -> None:
    """Raise ValueError when the last two axes of `x` are not `expected`."""
    if x.ndim < 2 or tuple(x.shape[-2:]) != expected:
        raise ValueError(
            f"{what} expects (..., H, W) = (..., {expected[0]}, {expected[1]}) for {padding}, "
            f"got shape {tuple(x.shape)}"
        )


def _edge_indices(padding: Padding) -> tuple[np.ndarray, np.ndarray]:
    """Source row and column indices that realise edge-replicate padding at the top and right."""
    rows = np.clip(np.arange(-padding.top, padding.height), 0, None)
    cols = np.clip(np.arange(padding.width + padding.right), None, padding.width - 1)
    return rows, cols


def pad_image(x: ArrayT, padding: Padding) -> ArrayT:
    """Pad the last two axes of an image `(..., H, W)` by replicating the edge rows and columns."""
    _check_size(x, padding, (padding.height, padding.width), "pad_image")
    rows, cols = _edge_indices(padding)
    if isinstance(x, torch.Tensor):
        return x.index_select(-2, torch.from_numpy(rows).to(x.device)).index_select(
            -1, torch.from_numpy(cols).to(x.device)
        )
    return np.take(np.take(x, rows, axis=-2), cols, axis=-1)


def pad_disparity(x: ArrayT, padding: Padding) -> ArrayT:
    """Pad the last two axes of a disparity `(..., H, W)` with zeros (invalid)."""
    _check_size(x, padding, (padding.height, padding.width), "pad_disparity")
    if isinstance(x, torch.Tensor):
        return torch.nn.functional.pad(x, (0, padding.right, padding.top, 0), mode="constant", value=0.0)
    widths = [(0, 0)] * (x.ndim - 2) + [(padding.top, 0), (0, padding.right)]
    return np.pad(x, widths, mode="constant", constant_values=0)


def unpad(x: ArrayT, padding: Padding) -> ArrayT:
    """Crop a padded `(..., H', W')` array or tensor back to `(..., H, W)`: `[top:, :W' − right]`."""
    _check_size(x, padding, padding.padded_shape, "unpad")
    return x[..., padding.top :, : padding.width]
