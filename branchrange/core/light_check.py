"""What light is a frame in? Brightness and sensor noise of the left image, to read confidences by.

The learned segmenter's confidence is a measured share of right cut points, and what is right depends
on the light: at dusk SGBM has a third of the signal, in haze a third of the contrast, at high gain
the noise shows the network stems that are not there. Calibrated under the renderer's own light only,
the confidence strayed from the share of right cut points twice as far at dusk and at high gain as in
that light (`benchmarks/results/segmenter.md`, "Confidence read in the frame's own light"). So a frame's light is
measured here, sorted into one of `LIGHTS`, and the segmenter reads its confidences through the
calibration measured in that light.

The measures (on the grey left image, `uint8`):
- `median_grey`: its median grey level (0..255).
- `noise_grey`: the sensor noise σ in grey levels: Immerkær's estimate (the mean absolute response of a
  Laplacian-difference kernel that cancels planes, × √(π/2) / 6) in each `NOISE_BLOCK_PX` block, and the
  `NOISE_PERCENTILE`th percentile over the blocks with no pixel at 0 or 255 (there the noise is clipped
  away). Texture raises a block's estimate, never lowers it, so the flattest blocks (sky, smooth bark,
  blur) read the noise itself.

The classes, in this order of precedence, with bounds between the light of the synthetic calibration
scenes and the changes of light that hurt (`light_changes`; measured on the 180 calibration and held-out
scenes, 1st–99th percentile):
- "dark": median grey < `DARK_BELOW` (the scenes' own light: 76–134; dusk: 22–40);
- "bright": median grey > `BRIGHT_ABOVE` (glare: 135–239, haze: 146–173);
- "noisy": noise > `NOISY_ABOVE` grey levels (high gain, σ 6: all 180 read 3.6–8.2; in their own light
  175 of the 180 read 0.6–3.0, the rest are wholly textured frames, leaves or bark to the edges);
- "normal": otherwise.
A real camera's light differs from the renderer's: the class only says which calibration a frame's
confidences go through, and is reported with each result (`FrameResult.masks.light`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

LIGHTS = ("normal", "dark", "bright", "noisy")
DARK_BELOW = 55.0
BRIGHT_ABOVE = 142.0
NOISY_ABOVE = 3.0
NOISE_BLOCK_PX = 16
NOISE_PERCENTILE = 5.0
#: Immerkær's kernel: the difference of two Laplacians, zero on any plane
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=np.float32)


@dataclass(frozen=True)
class LightReading:
    """A frame's light: `median_grey` (0..255), `noise_grey` (σ, grey levels) and its class in `LIGHTS`."""

    median_grey: float
    noise_grey: float
    light: str

    @property
    def measured(self) -> str:
        """What was measured, in words: "median grey 104, noise σ 0.8 grey levels"."""
        return f"median grey {self.median_grey:.0f}, noise σ {self.noise_grey:.1f} grey levels"

    @property
    def message(self) -> str:
        """A sentence for logs and users: what was measured and what it means for the confidences."""
        if self.light == "normal":
            return f"light normal ({self.measured})"
        return (
            f"light {self.light} ({self.measured}): fewer branches are found, and confidences are read through "
            f"the calibration measured in {self.light} light"
        )


def measure_light(image: np.ndarray) -> LightReading:
    """The `LightReading` of a `uint8 H×W×3` (RGB) or `H×W` grey image; ~1.2 ms at 640×360."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise ValueError(f"measure_light expects a uint8 H×W or H×W×3 image, got {image.dtype} {image.shape}")
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    # the median from the histogram: a sort of the frame's pixels costs ten times more
    median = float(np.searchsorted(np.cumsum(np.bincount(grey.ravel(), minlength=256)), (grey.size + 1) / 2))
    noise = noise_sigma(grey)
    return LightReading(median, noise, light_class(median, noise))


def noise_sigma(grey: np.ndarray) -> float:
    """Sensor noise σ (grey levels) of a `uint8 H×W` image: Immerkær's estimate over its flattest unclipped
    blocks (see the module docstring); 0 when the image has no such block (smaller than a block, all clipped)."""
    rows, cols = grey.shape[0] // NOISE_BLOCK_PX, grey.shape[1] // NOISE_BLOCK_PX
    if rows == 0 or cols == 0:
        return 0.0
    used = grey[: rows * NOISE_BLOCK_PX, : cols * NOISE_BLOCK_PX]
    response = cv2.filter2D(used, cv2.CV_16S, _NOISE_KERNEL, borderType=cv2.BORDER_REFLECT)  # exact: |r| ≤ 4080
    per_block = cv2.resize(np.abs(response).astype(np.float32), (cols, rows), interpolation=cv2.INTER_AREA)
    per_block *= np.sqrt(np.pi / 2) / 6
    blocks = used.reshape(rows, NOISE_BLOCK_PX, cols, NOISE_BLOCK_PX)
    seen = (blocks.min(axis=(1, 3)) > 0) & (blocks.max(axis=(1, 3)) < 255)
    return float(np.percentile(per_block[seen], NOISE_PERCENTILE)) if seen.any() else 0.0


def light_class(median_grey: float, noise_grey: float) -> str:
    """The class in `LIGHTS` of a frame's median grey level and noise σ (module docstring)."""
    if median_grey < DARK_BELOW:
        return "dark"
    if median_grey > BRIGHT_ABOVE:
        return "bright"
    if noise_grey > NOISY_ABOVE:
        return "noisy"
    return "normal"
