"""Changed light for a stereo pair: the same scene at dusk, in glare, in haze, under warm light or at high gain.

The learned segmenter's confidence is calibrated on synthetic scenes under the renderer's own light;
a field camera sees dawn, dusk, backlight and haze. Applying one of these changes to both images of a
pair (then computing stereo again) measures how much recall and the honesty of the confidence depend on
the light (`benchmarks/segmenter.py --light`). Each change acts on `uint8 H×W×3` images and returns
the same; the noise of `dusk` and `high_gain` comes from the generator passed in, so a run repeats.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: a change of light: (image `float32 H×W×3` in 0..255, generator) → image in 0..255 (not yet clipped)
LightChange = Callable[[np.ndarray, np.random.Generator], np.ndarray]

LIGHT_CHANGES: dict[str, LightChange] = {
    # a third of the light and the sensor's read noise, which is what is left of the signal at dusk
    "dusk": lambda image, rng: 0.3 * image + rng.normal(0.0, 2.0, image.shape),
    # overexposed: gain 1.8, the bright bark and sky clipped
    "glare": lambda image, rng: 1.8 * image,
    # airlight: contrast cut to 45 %, everything lifted toward a pale grey
    "haze": lambda image, rng: 0.45 * image + 0.55 * 205.0,
    # low sun: red up a quarter, blue down 30 % (RGB order)
    "warm": lambda image, rng: image * np.array([1.25, 1.0, 0.7], dtype=np.float32),
    # auto-exposure at high gain: normal brightness, noise of 6 grey levels
    "high_gain": lambda image, rng: image + rng.normal(0.0, 6.0, image.shape),
}


def changed_light(image: np.ndarray, change: str, rng: np.random.Generator) -> np.ndarray:
    """`uint8 H×W×3` `image` under the named `change` of `LIGHT_CHANGES`, rounded and clipped to 0..255."""
    if change not in LIGHT_CHANGES:
        raise ValueError(f"unknown light change {change!r}: one of {', '.join(LIGHT_CHANGES)}")
    changed = LIGHT_CHANGES[change](np.asarray(image, dtype=np.float32), rng)
    return np.asarray(np.clip(np.rint(changed), 0, 255), dtype=np.uint8)
