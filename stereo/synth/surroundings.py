"""What is behind and around the trees of a randomized scene: ground cover, a far tree line, buildings,
nets and orchard structures (posts, wires, stakes, rods, irrigation pipes).

Everything here is background (mask id 0). Planes are `PlaneLayer`s given in the camera frame;
structures are `hardware.HardwarePiece`s in the world frame (y down, camera at the origin, looking
along +z), drawn as cones like the trees. The rows of trees behind are grown trees, placed by
`stereo.synth.randomized`.
"""

from __future__ import annotations

import numpy as np

from stereo.synth.hardware import HARDWARE_COLOURS, HardwarePiece, orchard_hardware, surface_tile
from stereo.synth.planes import PlaneLayer
from stereo.synth.scene import CameraFrame
from stereo.synth.textures import TILE_SIZE, MipTile, foliage_tile, ground_tile, periodic_noise, unit_range

#: ground covers: two albedos (linear RGB) mixed in patches
GROUND_COVERS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "grass": ((0.22, 0.36, 0.10), (0.30, 0.34, 0.14)),
    "dry_grass": ((0.48, 0.42, 0.24), (0.30, 0.26, 0.17)),
    "bare_soil": ((0.36, 0.28, 0.19), (0.22, 0.17, 0.12)),
    "mulch": ((0.30, 0.20, 0.12), (0.14, 0.10, 0.07)),
    "snow": ((0.88, 0.90, 0.94), (0.70, 0.72, 0.78)),
}
#: the ground of scenes that do not randomize it
DEFAULT_COVER = "grass"
#: what may stand behind the trees, beyond the rows: a wood, buildings, or nothing (open sky to the horizon)
BACKDROPS = ("wood", "buildings", "open")
_X, _Y, _Z = np.eye(3)


def ground_layer(rng: np.random.Generator, cover: str, frame: CameraFrame, ground_y: float) -> PlaneLayer:
    """The ground `ground_y` m below the camera, covered with `cover` (one of `GROUND_COVERS`)."""
    first, second = (np.array(c) * rng.uniform(0.8, 1.15) for c in GROUND_COVERS[cover])
    return PlaneLayer(
        frame.point(ground_y * _Y),
        frame.direction(_X),
        frame.direction(_Z),
        MipTile(ground_tile(rng, tuple(first), tuple(second))),
        rng.uniform(0.6, 2.0),
        0.8,
    )


def wood_layer(rng: np.random.Generator, frame: CameraFrame, ground_y: float, distance_m: float) -> PlaneLayer:
    """A wall of far foliage `distance_m` ahead, its crown line 6–20 m up, reaching down to the ground."""
    hue = np.clip(np.array([0.16, 0.28, 0.10]) * rng.uniform(0.6, 1.3) + rng.normal(0, 0.03, 3), 0.02, 1)
    foliage = foliage_tile(rng, tuple(hue), rng.uniform(0.8, 0.97))
    bumps = np.abs(np.sin(np.linspace(0.0, np.pi * rng.integers(25, 50), 512, endpoint=False)))  # crowns 4–8 m
    profile = rng.uniform(6.0, 18.0) + 2.0 * bumps + 1.5 * periodic_noise(rng, 4.0, 4.0, size=512)[0]
    return PlaneLayer(
        frame.point(np.array([0.0, ground_y, distance_m])),
        frame.direction(_X),
        frame.direction(-_Y),
        MipTile(foliage[:, :, :3]),
        rng.uniform(4.0, 8.0),
        0.5,
        np.ascontiguousarray(foliage[:, :, 3:]),
        profile,
        200.0,
    )


def buildings_layer(rng: np.random.Generator, frame: CameraFrame, ground_y: float, distance_m: float) -> PlaneLayer:
    """Walls `distance_m` ahead: buildings 3–12 m tall and 6–25 m wide with gaps, rendered walls with windows."""
    period, samples = 120.0, 512
    u = np.arange(samples) * period / samples
    heights = np.zeros(samples)
    position = rng.uniform(0.0, 10.0)
    while position < period:
        width = rng.uniform(6.0, 25.0)
        heights[(u >= position) & (u < position + width)] = rng.uniform(3.0, 12.0)
        position += width + rng.uniform(0.0, 15.0)
    wall = np.array(HARDWARE_COLOURS[str(rng.choice(["concrete", "white_plastic", "red_paint"]))])
    return PlaneLayer(
        frame.point(np.array([0.0, ground_y, distance_m])),
        frame.direction(_X),
        frame.direction(-_Y),
        MipTile(_facade_tile(rng, wall)),
        rng.uniform(3.0, 6.0),
        0.9,
        None,
        heights,
        period,
    )


def _facade_tile(rng: np.random.Generator, wall: np.ndarray) -> np.ndarray:
    """RGB `S×S×3`: a weathered wall with a grid of dark windows."""
    stains = unit_range(periodic_noise(rng, 4.0, 4.0))
    colour = wall[None, None, :] * (0.8 + 0.3 * stains[..., None])
    cells = int(rng.integers(2, 5))
    cell = TILE_SIZE // cells
    rows, cols = np.mgrid[0:TILE_SIZE, 0:TILE_SIZE]
    window = ((rows % cell) > 0.3 * cell) & ((rows % cell) < 0.75 * cell)
    window &= ((cols % cell) > 0.25 * cell) & ((cols % cell) < 0.75 * cell)
    colour[window] = np.array([0.08, 0.1, 0.12]) * rng.uniform(0.6, 2.0)
    return np.clip(colour, 0.0, 1.0).astype(np.float32)


def net_layer(rng: np.random.Generator, frame: CameraFrame, ground_y: float, row_distance_m: float) -> PlaneLayer:
    """A wind or bird net hanging along the row 0.3–1 m behind the near trees; its mesh (3–8 cm cells of dark
    or white thread) is the layer's alpha. (Hail netting overhead is a veil over the sky: `lighting.SunSky`.)"""
    cell_m = rng.uniform(0.03, 0.08)
    cells = 8
    rows, cols = np.mgrid[0:TILE_SIZE, 0:TILE_SIZE]
    line = max(1, int(round(TILE_SIZE / cells * rng.uniform(0.06, 0.15))))
    thread = ((rows % (TILE_SIZE // cells)) < line) | ((cols % (TILE_SIZE // cells)) < line)
    shade = np.array([0.08, 0.08, 0.09]) if rng.random() < 0.5 else np.array([0.85, 0.86, 0.86])
    tile = np.broadcast_to(shade, (TILE_SIZE, TILE_SIZE, 3)).astype(np.float32)
    alpha = thread.astype(np.float32)[..., None]
    return PlaneLayer(
        frame.point(np.array([0.0, ground_y, row_distance_m + rng.uniform(0.3, 1.0)])),
        frame.direction(_X),
        frame.direction(-_Y),
        MipTile(tile),
        cells * cell_m,
        0.8,
        np.ascontiguousarray(alpha),
    )


def structures(
    rng: np.random.Generator, trunk_foot: np.ndarray, trunk_radius: float, ground_y: float, row_axis: np.ndarray
) -> list[HardwarePiece]:
    """Posts, wires, a stake and rods around the tree at world `trunk_foot` (`hardware.orchard_hardware`),
    and, with an even chance, an irrigation pipe along the row (`row_axis`, a unit world vector) at the
    trees' feet or hanging from the lowest wire."""
    pieces = orchard_hardware(rng, trunk_foot, trunk_radius, ground_y, row_axis)
    if rng.random() < 0.5:
        height = rng.choice([rng.uniform(0.02, 0.1), rng.uniform(0.3, 0.6)])
        offset = rng.uniform(-0.2, 0.2) * np.array([row_axis[2], 0.0, -row_axis[0]])
        start = trunk_foot + offset - 12.0 * row_axis - height * _Y
        colour = HARDWARE_COLOURS["black_plastic"]
        pieces.append(
            HardwarePiece("pipe", start, row_axis, 24.0, rng.uniform(0.006, 0.011), surface_tile(rng, colour))
        )
    return pieces
