"""What the branch segmenter network (`BranchNet`) takes and gives, in NumPy: the per-frame side of it.

Input: 5 channels at the frame's size — RGB, disparity divided by its 95th percentile (so the
network sees the scene's relative depth whatever the camera's focal length and baseline), and
the disparity's validity; H and W padded to multiples of `STRIDE`. Output: logits `(3, H, W)` for
`CLASSES`. The network itself, in PyTorch, is `branchrange.learning.branchnet`: training and export
need it, a frame does not (the onboard loop runs the exported ONNX file without importing torch).
"""

from __future__ import annotations

import cv2
import numpy as np

CLASSES = ("background", "trunk", "branch")
IN_CHANNELS = 5
#: total downsampling of the encoder: inputs must be multiples of this
STRIDE = 16
_RGB_MEAN, _RGB_STD = 0.45, 0.25
#: the normalized value of each 8-bit colour value, in the float32 arithmetic of `(v / 255 − mean) / std`
_RGB_TABLE = ((np.arange(256, dtype=np.float32) / 255.0 - _RGB_MEAN) / _RGB_STD).astype(np.float32)


def disparity_scale(disparity: np.ndarray) -> float:
    """95th percentile (px) of a frame's valid disparity, 1 when none is valid: what `network_input` divides by."""
    values = disparity[np.isfinite(disparity) & (disparity > 0)]
    if values.size == 0:
        return 1.0
    # np.percentile's linear interpolation, step for step, from one partition: np.percentile selects 4 ranks,
    # and is ~10× slower on the many equal values of a disparity resized by nearest neighbour
    position = (values.size - 1) * 0.95
    below = int(position)
    gamma = position - below
    values.partition(below)
    low = values[below]
    high = values[below + 1 :].min() if below + 1 < values.size else low
    step = high - low
    return float(high - step * (1 - gamma) if gamma >= 0.5 else low + step * gamma)


def network_input(left: np.ndarray, disparity: np.ndarray, scale: float | None = None, stride: int = 1) -> np.ndarray:
    """`float32 (5, H', W')` input of a rectified left image `uint8 H×W×3` and its disparity `H×W` px; H', W'
    are H, W rounded up to multiples of `stride` (`STRIDE`: what the network takes), edge-padded at the
    bottom/right as `padded_to_stride` pads.

    Disparity is divided by `scale` (default: `disparity_scale` of this disparity; training crops
    pass their whole frame's) and clipped to [0, 2]: a scale-free relative inverse depth. Invalid
    disparity (0, negative, non-finite) is 0 with validity 0.
    """
    disparity = np.asarray(disparity, dtype=np.float32)
    height, width = disparity.shape
    features = np.empty((IN_CHANNELS, -(-height // stride) * stride, -(-width // stride) * stride), np.float32)
    frame = features[:, :height, :width]  # written in place: no full-frame temporaries, no copy to pad
    for channel, values in enumerate(cv2.split(left)):  # cv2's planes and lookup: ~2× faster than numpy's
        frame[channel] = cv2.LUT(values, _RGB_TABLE)
    valid = np.isfinite(disparity) & (disparity > 0)
    scale = disparity_scale(disparity) if scale is None else scale
    np.divide(disparity, max(scale, 1e-3), out=frame[3])
    np.clip(frame[3], 0.0, 2.0, out=frame[3])
    frame[3][~valid] = 0.0
    frame[4] = valid
    features[:, height:, :width] = features[:, height - 1 : height, :width]
    features[:, :, width:] = features[:, :, width - 1 : width]
    return features


def padded_to_stride(array: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    """`(C, H', W')` edge-padded at the bottom/right to multiples of `STRIDE`, and the original (H, W)."""
    _, h, w = array.shape
    pad_h, pad_w = (-h) % STRIDE, (-w) % STRIDE
    return np.pad(array, ((0, 0), (0, pad_h), (0, pad_w)), mode="edge"), (h, w)
