"""Procedural bark and wood over a wide range, for the randomized scenes: colour, relief and what grows on it.

A `BarkLook` is drawn per tree: a base colour from grey through brown and red-brown to olive and
silver, furrow depth and spacing (smooth cherry to deeply ridged old wood), lenticels, lichen,
moss on one side, a pruning wound (pale wood in a dark callus ring; the tile repeats round the
stem, so one is plenty), and wet bark (darker, more saturated). Young shoots get their own tile:
smooth, lighter or redder than the old wood, with lenticels. Tiles follow `stereo.synth.textures`:
columns run along the branch axis, rows around it, so one band of rows is one side of the trunk
(where moss grows).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereo.synth.textures import TILE_SIZE, periodic_noise, unit_range

#: base colours (linear RGB albedo) bark is drawn around; a drawn look jitters its family's colour
BARK_COLOURS: dict[str, tuple[float, float, float]] = {
    "grey": (0.42, 0.41, 0.39),
    "brown": (0.33, 0.24, 0.17),
    "red_brown": (0.40, 0.20, 0.14),
    "dark": (0.17, 0.14, 0.12),
    "olive": (0.36, 0.35, 0.24),
    "silver": (0.62, 0.61, 0.58),
}
#: the look used when bark is not randomized: a plain grey-brown with shallow furrows
PLAIN_COLOUR = (0.38, 0.32, 0.26)
_LICHEN = np.array([0.55, 0.60, 0.45])
_MOSS = np.array([0.16, 0.30, 0.07])
_WOUND = np.array([0.75, 0.62, 0.42])


@dataclass(frozen=True)
class BarkLook:
    """One tree's bark: `colour` RGB, `relief` furrow depth (0 smooth – 0.8 deep), `furrow_cycles` furrows
    around a tile, `lenticels`, `lichen` and `moss` cover (0–1), `wounds` per tile, `wet`, and `young` the
    RGB of its young shoots."""

    colour: tuple[float, float, float]
    relief: float
    furrow_cycles: float
    lenticels: bool
    lichen: float
    moss: float
    wounds: int
    wet: bool
    young: tuple[float, float, float]


def plain_look() -> BarkLook:
    """The fixed bark of scenes that do not randomize it."""
    return BarkLook(PLAIN_COLOUR, 0.4, 14.0, False, 0.0, 0.0, 0, False, PLAIN_COLOUR)


def draw_look(rng: np.random.Generator) -> BarkLook:
    """A random bark look (every range in the module docstring)."""
    family = BARK_COLOURS[str(rng.choice(list(BARK_COLOURS)))]
    colour = np.clip(np.array(family) * rng.uniform(0.7, 1.3) + rng.normal(0.0, 0.03, 3), 0.04, 0.9)
    young = colour * rng.uniform(1.0, 1.5) + np.array([rng.uniform(0.0, 0.2), rng.uniform(-0.05, 0.08), 0.0])
    return BarkLook(
        _rgb(colour),
        float(rng.uniform(0.0, 0.8)),
        float(rng.uniform(6.0, 30.0)),
        bool(rng.random() < 0.4),
        float(rng.uniform(0.0, 0.5) if rng.random() < 0.5 else 0.0),
        float(rng.uniform(0.0, 0.6) if rng.random() < 0.35 else 0.0),
        int(rng.random() < 0.3),
        bool(rng.random() < 0.25),
        _rgb(np.clip(young, 0.04, 0.9)),
    )


def _rgb(colour: np.ndarray) -> tuple[float, float, float]:
    """An RGB array `(3,)` as a tuple of floats."""
    return float(colour[0]), float(colour[1]), float(colour[2])


def old_wood_tile(rng: np.random.Generator, look: BarkLook) -> np.ndarray:
    """RGB `S×S×3` in [0, 1] of the trunk's and old branches' bark."""
    furrows = np.exp(-((periodic_noise(rng, 2.5, look.furrow_cycles, slope=2.5) / 0.45) ** 2))
    grain = unit_range(periodic_noise(rng, 48.0, 48.0, slope=1.5))
    patches = unit_range(periodic_noise(rng, 2.0, 2.0))
    shade = (0.75 + 0.4 * grain) * (1.0 - look.relief * furrows)
    colour = np.array(look.colour)[None, None, :] * shade[..., None] * (0.85 + 0.3 * patches[..., None])
    colour = _overgrown(rng, colour, look)
    for _ in range(look.wounds):
        colour = _wound(rng, colour)
    return _finished(colour, look)


def young_wood_tile(rng: np.random.Generator, look: BarkLook) -> np.ndarray:
    """RGB `S×S×3` in [0, 1] of young shoots: smooth, the look's young colour, lenticels when it has them."""
    grain = unit_range(periodic_noise(rng, 30.0, 8.0, slope=1.5))
    colour = np.array(look.young)[None, None, :] * (0.85 + 0.3 * grain[..., None])
    if look.lenticels:
        colour = _lenticels(rng, colour)
    return _finished(colour, look)


def _overgrown(rng: np.random.Generator, colour: np.ndarray, look: BarkLook) -> np.ndarray:
    """Lenticels, lichen patches all round and moss on one side (a band of rows) over `colour`."""
    if look.lenticels:
        colour = _lenticels(rng, colour)
    if look.lichen > 0:
        field = unit_range(periodic_noise(rng, 6.0, 6.0, slope=1.8))
        cover = np.clip((field - (1.0 - look.lichen)) * 4.0, 0.0, 1.0)[..., None]
        colour = colour * (1 - cover) + _LICHEN * rng.uniform(0.7, 1.1) * cover
    if look.moss > 0:
        side = 0.5 + 0.5 * np.cos(2 * np.pi * (np.arange(TILE_SIZE) / TILE_SIZE - rng.uniform()))
        field = unit_range(periodic_noise(rng, 10.0, 10.0, slope=1.5))
        cover = np.clip((field * side[:, None] - (1.0 - look.moss)) * 5.0, 0.0, 1.0)[..., None]
        colour = colour * (1 - cover) + _MOSS * rng.uniform(0.7, 1.3) * cover
    return colour


def _lenticels(rng: np.random.Generator, colour: np.ndarray) -> np.ndarray:
    """Short dashes around the stem (long across the axis), lighter or darker than the bark."""
    marks = periodic_noise(rng, 40.0, 5.0, slope=3.0) > 1.8
    colour = colour.copy()
    colour[marks] *= rng.choice([0.6, 1.2])
    return colour


def _wound(rng: np.random.Generator, colour: np.ndarray) -> np.ndarray:
    """A pruning wound: a disc of pale wood inside a dark callus ring, somewhere on the tile."""
    rows, cols = np.mgrid[0:TILE_SIZE, 0:TILE_SIZE]
    centre = rng.uniform(0, TILE_SIZE, 2)
    d_row = np.minimum(np.abs(rows - centre[0]), TILE_SIZE - np.abs(rows - centre[0]))
    d_col = np.minimum(np.abs(cols - centre[1]), TILE_SIZE - np.abs(cols - centre[1]))
    radius = rng.uniform(6.0, 16.0)
    distance = np.hypot(d_row, d_col)
    wood = _WOUND * rng.uniform(0.6, 1.1) * rng.uniform(0.5, 1.0)  # pale fresh, or greyed old cut
    colour = colour.copy()
    colour[distance < radius] = wood
    ring = (distance >= radius) & (distance < radius * 1.25)
    colour[ring] *= 0.5
    return colour


def _finished(colour: np.ndarray, look: BarkLook) -> np.ndarray:
    """Wet bark is darker and more saturated; clipped to [0, 1] float32."""
    if look.wet:
        grey = colour.mean(axis=2, keepdims=True)
        colour = (grey + 1.4 * (colour - grey)) * 0.55
    return np.asarray(np.clip(colour, 0.0, 1.0), dtype=np.float32)
