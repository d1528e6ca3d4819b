"""The "orchard" domain (`SynthOptions.domain`): a tree form, barks, leaves and light the shipped segmenter never saw.

The shipped `BranchNet` was trained on one scene family ("park"): a free-standing tree whose branches leave the
trunk at any azimuth, six bark kinds of furrowed noise, green to autumn leaves, a sun 15–70° high or a grey
overcast. An integrator's orchard differs in all of these at once, so this domain changes all of them, each
by parameters of its own (nothing here is drawn in a "park" scene, whose seeds render as before):

- tree form: an espalier (trellis-trained) tree — an upright trunk whose branches leave it in tiers, nearly
  level and along the row, each tier tied to a trellis wire (`ESPALIER_ELEVATION_DEG`, `ESPALIER_AZIMUTH_DEG`);
- barks (`ORCHARD_BARKS`, `orchard_bark_tile`): pine-like plates split by deep cracks across and along the axis,
  cherry-like smooth bark with bands of lenticels around the axis, and green, moss-covered bark;
- leaves (`ORCHARD_LEAF_COLOURS`): copper-red, blue-grey and pale lime blades;
- the row: trellis wires, posts and stakes around the tree always (`stereo.synth.hardware`), a mown grass
  alley and a row of espalier trees behind (4.5–8 m: background, mask id 0, beyond the working range);
- light (`orchard_light`): a low warm sun (3–14° high, orange) or a dim blue-grey overcast.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereo.synth.textures import periodic_noise, unit_range

#: orchard barks: base RGB albedo in [0, 1] and the pattern drawn on it (`orchard_bark_tile`)
ORCHARD_BARKS: dict[str, tuple[tuple[float, float, float], str]] = {
    "pine_plates": ((0.55, 0.32, 0.20), "plates"),
    "cherry_banded": ((0.40, 0.17, 0.14), "bands"),
    "mossy": ((0.30, 0.34, 0.18), "moss"),
    "silver_plates": ((0.62, 0.60, 0.58), "plates"),
}
#: leaf blade colours (linear RGB) of the orchard's varieties
ORCHARD_LEAF_COLOURS: dict[str, tuple[float, float, float]] = {
    "copper": (0.42, 0.13, 0.10),
    "blue_grey": (0.22, 0.32, 0.33),
    "lime": (0.55, 0.66, 0.20),
}
#: an espalier branch leaves the trunk this many degrees above the horizontal (negative: below)
ESPALIER_ELEVATION_DEG = (-8.0, 12.0)
#: and this many degrees off the row's direction, either way along the row
ESPALIER_AZIMUTH_DEG = 25.0
#: the trunk leans at most this much (the axis's horizontal share): trained trees stand upright
TRUNK_LEAN = 0.03


def orchard_bark_tile(rng: np.random.Generator, kind: str) -> np.ndarray:
    """RGB bark `S×S×3` (columns along the branch axis, rows around it, like `textures.bark_tile`) of one of
    `ORCHARD_BARKS`: "plates" — flat plates with deep dark cracks between them, longer along the axis; "bands" —
    smooth, slightly glossy bark with thin pale bands of lenticels running around the axis; "moss" — bark half
    covered in green moss cushions."""
    base, pattern = ORCHARD_BARKS[kind]
    base_rgb = np.clip(np.array(base) * rng.uniform(0.85, 1.15) + rng.normal(0, 0.03, 3), 0.03, 0.95)
    if pattern == "plates":
        cells = periodic_noise(rng, 6.0, 14.0, slope=3.0)
        cracks = np.exp(-((cells / 0.18) ** 2)) + np.exp(-((periodic_noise(rng, 10.0, 4.0, slope=3.0) / 0.12) ** 2))
        plate_shade = 0.85 + 0.3 * unit_range(periodic_noise(rng, 8.0, 8.0, slope=2.0))
        shade = plate_shade * (1.0 - 0.75 * np.clip(cracks, 0.0, 1.0))
        colour = base_rgb[None, None, :] * shade[..., None]
    elif pattern == "bands":
        sheen = 0.9 + 0.25 * unit_range(periodic_noise(rng, 1.5, 30.0, slope=2.0))
        colour = base_rgb[None, None, :] * sheen[..., None]
        bands = periodic_noise(rng, 24.0, 1.2, slope=3.0) > 1.4  # thin stripes around the axis
        colour[bands] = 0.5 * colour[bands] + 0.5 * np.array([0.70, 0.62, 0.52])
    else:
        grain = 0.75 + 0.4 * unit_range(periodic_noise(rng, 40.0, 40.0, slope=1.5))
        colour = base_rgb[None, None, :] * grain[..., None]
        moss = np.clip((unit_range(periodic_noise(rng, 3.0, 5.0)) - 0.45) * 4.0, 0.0, 1.0)[..., None]
        cushion = (
            np.array([0.20, 0.42, 0.08])
            * (0.7 + 0.5 * unit_range(periodic_noise(rng, 60.0, 60.0, slope=1.2)))[..., None]
        )
        colour = colour * (1 - moss) + cushion * moss
    return np.clip(colour, 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class OrchardLight:
    """The sky and sun of an orchard scene: zenith / horizon / cloud colours (linear RGB), cloud cover share,
    the sun's colour and elevation (rad) and the ambient light's colour."""

    zenith: np.ndarray
    horizon: np.ndarray
    cloud_rgb: np.ndarray
    cover: float
    sun_rgb: np.ndarray
    elevation_rad: float
    ambient: np.ndarray


def orchard_light(rng: np.random.Generator) -> OrchardLight:
    """A low warm sun (60 %: 3–14° high, orange, long shadows, a yellow-orange horizon) or a dim blue-grey
    overcast (40 %) — light the park scenes, whose sun stands 15–70° high in white light, never have."""
    if rng.random() < 0.6:
        return OrchardLight(
            np.array([0.30, 0.42, 0.70]) * rng.uniform(0.8, 1.0),
            np.array([0.95, 0.70, 0.42]),
            np.array([0.95, 0.72, 0.55]),
            float(rng.uniform(0.05, 0.4)),
            np.array([1.0, 0.62, 0.34]) * rng.uniform(0.8, 1.1),
            float(np.radians(rng.uniform(3.0, 14.0))),
            np.array([0.28, 0.30, 0.42]) * rng.uniform(0.8, 1.1),
        )
    return OrchardLight(
        np.array([0.52, 0.58, 0.68]) * rng.uniform(0.85, 1.05),
        np.array([0.66, 0.71, 0.78]),
        np.array([0.45, 0.48, 0.55]),
        float(rng.uniform(0.5, 0.9)),
        np.array([0.85, 0.90, 1.0]) * rng.uniform(0.05, 0.15),
        float(np.radians(rng.uniform(20.0, 60.0))),
        np.array([0.50, 0.58, 0.72]) * rng.uniform(0.6, 0.85),
    )
