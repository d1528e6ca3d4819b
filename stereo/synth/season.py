"""Leaves, blossom and fruit on a grown tree's shoot tips, by season, for the randomized scenes.

Seasons (`SEASONS`): 'dormant' (bare wood: the pruning season), 'blossom' (white to pink flowers in
clusters, a few young leaves), 'leaf' (green blades), 'fruit' (leaves and round fruit), 'autumn'
(yellow to orange leaves, some fallen). Leaves and blossom carry `LEAF_ID`; fruit is background
(id 0): neither is wood. Fruit are short capped cylinders facing the camera, so they look round.
"""

from __future__ import annotations

import numpy as np

from stereo.synth.cones import BarkMaterial, Cone
from stereo.synth.hardware import surface_tile
from stereo.synth.leaves import Leaf
from stereo.synth.primitives import cross3, unit
from stereo.synth.textures import MipTile
from stereo.synth.truth import LEAF_ID

SEASONS = ("dormant", "blossom", "leaf", "fruit", "autumn")
#: how often each season is drawn when seasons are randomized (pruning is mostly done in winter)
SEASON_WEIGHTS = (0.45, 0.12, 0.2, 0.13, 0.1)
_LEAF_RGB = {
    "blossom": (0.35, 0.55, 0.15),
    "leaf": (0.15, 0.32, 0.08),
    "fruit": (0.14, 0.28, 0.08),
    "autumn": (0.70, 0.50, 0.12),
}
_FRUIT_RGB = ((0.60, 0.06, 0.05), (0.45, 0.60, 0.12), (0.80, 0.65, 0.15))


def fruit_skin(rng: np.random.Generator) -> MipTile:
    """The skin of a scene's fruit: red, green or yellow."""
    return MipTile(surface_tile(rng, _FRUIT_RGB[int(rng.integers(len(_FRUIT_RGB)))]))


def foliage(
    rng: np.random.Generator, season: str, tips: np.ndarray, headings: np.ndarray, per_tip: int, skin: MipTile
) -> tuple[list[Leaf], list[Cone]]:
    """Leaves (and blossom) and fruit cones (of `skin`, `fruit_skin`) of `season` around shoot `tips` `(N, 3)`
    growing along unit `headings` `(N, 3)`, camera frame (m); about `per_tip` leaves on each tip."""
    if season == "dormant" or len(tips) == 0:
        return [], []
    leaves: list[Leaf] = []
    cones: list[Cone] = []
    hue = np.array(_LEAF_RGB[season]) * rng.uniform(0.75, 1.25, 3)
    size = rng.uniform(0.025, 0.05)
    petal = np.array([0.95, 0.9, 0.92]) if rng.random() < 0.6 else np.array([0.95, 0.7, 0.8])
    for tip, heading in zip(tips, headings):
        count = int(rng.integers(max(1, per_tip // 2), per_tip + 1))
        if season == "blossom":
            count = max(1, count // 3)
        for _ in range(count):
            leaves.append(_blade(rng, tip, heading, size, hue * rng.uniform(0.8, 1.2), 0.4))
        if season == "blossom":
            centre = tip + rng.normal(0.0, 0.02, 3)
            for _ in range(5 * int(rng.integers(1, 4))):
                leaves.append(_blade(rng, centre, rng.normal(size=3), 0.008, petal * rng.uniform(0.9, 1.05), 0.8))
        if season == "fruit" and rng.random() < 0.3:
            radius = rng.uniform(0.025, 0.04)
            centre = tip + heading * radius + np.array([0.0, radius, 0.0])
            toward = -unit(centre) if np.linalg.norm(centre) > 0 else np.array([0.0, 0.0, -1.0])
            material = BarkMaterial(skin, 1, 0.3)
            cones.append(Cone(centre - toward * radius, toward, 1.6 * radius, radius, 0.85 * radius, material, 0))
    return leaves, cones


def _blade(rng: np.random.Generator, anchor: np.ndarray, heading: np.ndarray, size: float, colour: np.ndarray,
           width: float) -> Leaf:  # fmt: skip
    """A blade `size` m half-long hanging off `anchor` roughly along `heading`, any tilt."""
    e1 = unit(heading + rng.normal(0.0, 0.8, 3))
    normal = unit(cross3(e1, rng.normal(size=3)))
    centre = anchor + e1 * size * rng.uniform(0.6, 1.2)
    return Leaf(centre, normal, e1, size, size * width, np.clip(colour, 0.0, 1.0), LEAF_ID)
