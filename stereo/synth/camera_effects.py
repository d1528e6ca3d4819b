"""What a real camera does to a rendered view: exposure and white-balance drift, vignetting, defocus,
motion blur, sensor noise, and JPEG or H.264-like compression.

Images are float32 `H×W×3` linear colour in about [0, 1] until `quantised`, then uint8 RGB. The
ZED Mini's noise is modelled as read noise plus shot noise (variance grows with the level), scaled
by the analogue gain, and slightly blurred as demosaicing does (neighbouring pixels' noise is
correlated, and chroma noise is visible in dim light). H.264-like artefacts: 4:2:0 chroma and a
4×4 block transform (H.264's integer transform is a DCT approximation) with a quantiser step.
"""

from __future__ import annotations

import cv2
import numpy as np

_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)
#: the orthonormal 4-point DCT-II matrix (rows: basis functions)
_DCT4 = np.array(
    [[np.sqrt((1 if k == 0 else 2) / 4) * np.cos(np.pi * (2 * n + 1) * k / 8) for n in range(4)] for k in range(4)],
    dtype=np.float32,
)


def exposed(image: np.ndarray, gain: float, white_balance: np.ndarray) -> np.ndarray:
    """`image` × `gain` × per-channel `white_balance` `(3,)` gains (not clipped: optics blur before the sensor
    saturates)."""
    return (image * np.float32(gain) * white_balance.astype(np.float32)[None, None, :]).astype(np.float32)


def metered_gain(image: np.ndarray, target: float) -> float:
    """The gain (0.5–8) that brings the mean luma of linear `image` `H×W×3` to `target`: auto-exposure
    metered on the whole frame (so a bright sky darkens a backlit tree)."""
    luma = float((image.reshape(-1, 3).mean(axis=0) * _LUMA).sum())
    return float(np.clip(target / max(luma, 1e-3), 0.5, 8.0))


def vignetted(image: np.ndarray, strength: float) -> np.ndarray:
    """`image` darkened toward the corners: × (1 − strength·r²), r = 1 at the corners."""
    height, width = image.shape[:2]
    y = (np.arange(height, dtype=np.float32) - (height - 1) / 2) / ((height - 1) / 2)
    x = (np.arange(width, dtype=np.float32) - (width - 1) / 2) / ((width - 1) / 2)
    r2 = (x[None, :] ** 2 * width**2 + y[:, None] ** 2 * height**2) / (width**2 + height**2)
    return np.asarray(image * (1.0 - np.float32(strength) * r2)[..., None], dtype=np.float32)


def defocused(image: np.ndarray, depth_m: np.ndarray, focus_m: float, blur_px_per_dioptre: float) -> np.ndarray:
    """Depth-of-field blur: each pixel's circle of confusion is `blur_px_per_dioptre · |1/Z − 1/focus|` px
    (radius; `depth_m` `H×W`, inf on sky); the image blends disc-blurred copies of radius 0–4 px by it."""
    with np.errstate(divide="ignore"):
        inverse = np.where(np.isfinite(depth_m), 1.0 / np.maximum(depth_m, 1e-3), 0.0)
    radius = np.clip(blur_px_per_dioptre * np.abs(inverse - 1.0 / focus_m), 0.0, 4.0).astype(np.float32)
    out = image.copy()
    previous = image
    for level in range(1, 5):
        size = 2 * level + 1
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)).astype(np.float32)
        blurred = cv2.filter2D(image, -1, disc / disc.sum(), borderType=cv2.BORDER_REFLECT)
        weight = np.clip(radius - (level - 1), 0.0, 1.0)[..., None]  # between level−1 and level px
        out = np.where(weight > 0, previous * (1 - weight) + blurred * weight, out)
        previous = blurred
    return out.astype(np.float32)


def motion_blurred(image: np.ndarray, length_px: float, angle_rad: float) -> np.ndarray:
    """A straight streak of `length_px` at `angle_rad` (the rig moving or turning during the exposure)."""
    if length_px < 1.0:
        return image
    size = int(np.ceil(length_px)) | 1
    kernel = np.zeros((size, size), dtype=np.float32)
    centre = (size - 1) / 2
    for t in np.linspace(-length_px / 2, length_px / 2, 4 * size):
        kernel[int(round(centre + t * np.sin(angle_rad))), int(round(centre + t * np.cos(angle_rad)))] = 1.0
    return cv2.filter2D(image, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)


def noisy(image: np.ndarray, rng: np.random.Generator, read_std: float, shot: float, gain: float) -> np.ndarray:
    """Sensor noise on `image` (float, 0–1 levels): std `gain · sqrt(read² + shot · level)` in 8-bit levels /
    255, per channel, with a third of it shared by the channels, blurred by σ 0.6 px as demosaicing does."""
    image = np.clip(image, 0.0, 1.0)
    levels = image * 255.0
    std = np.float32(min(gain, 8.0)) * np.sqrt(read_std**2 + shot * levels) / 255.0
    colour = rng.standard_normal(image.shape, dtype=np.float32)
    shared = rng.standard_normal(image.shape[:2], dtype=np.float32)[..., None]
    field = cv2.GaussianBlur(0.9 * colour + 0.45 * shared, (0, 0), 0.6) * np.float32(1.6)
    return (image + std * field).astype(np.float32)


def quantised(image: np.ndarray) -> np.ndarray:
    """Float `H×W×3` in [0, 1] → uint8 RGB."""
    return np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)


def jpeg_compressed(image: np.ndarray, quality: int) -> np.ndarray:
    """uint8 RGB `image` through a JPEG encode and decode at `quality` (1–100)."""
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("OpenCV could not JPEG-encode the image")
    decoded = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if decoded is None:
        raise RuntimeError("OpenCV could not decode its own JPEG")
    return cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB)


def h264_like(image: np.ndarray, step: float) -> np.ndarray:
    """uint8 RGB `image` with H.264-like intra coding artefacts: 4:2:0 chroma and every 4×4 block's DCT
    coefficients quantised with `step` (grey levels; the DC coefficient with half of it)."""
    ycc = cv2.cvtColor(image, cv2.COLOR_RGB2YCrCb).astype(np.float32)
    height, width = image.shape[:2]
    for channel in (1, 2):
        small = cv2.resize(ycc[:, :, channel], (max(1, width // 2), max(1, height // 2)), interpolation=cv2.INTER_AREA)
        ycc[:, :, channel] = cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR)
    h4, w4 = height - height % 4, width - width % 4
    blocks = ycc[:h4, :w4].reshape(h4 // 4, 4, w4 // 4, 4, 3).transpose(0, 2, 4, 1, 3)
    coefficients = _DCT4 @ blocks @ _DCT4.T
    steps = np.full((4, 4), step, dtype=np.float32)
    steps[0, 0] = step / 2
    coefficients = np.rint(coefficients / steps) * steps
    ycc[:h4, :w4] = (_DCT4.T @ coefficients @ _DCT4).transpose(0, 3, 1, 4, 2).reshape(h4, w4, 3)
    return cv2.cvtColor(np.clip(np.rint(ycc), 0, 255).astype(np.uint8), cv2.COLOR_YCrCb2RGB)
