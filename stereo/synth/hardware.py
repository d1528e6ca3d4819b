"""Orchard hardware around the tree: trellis wires, posts, stakes and painted rods — things a pruner must not cut.

Orchards are full of straight, thin, man-made structures at the tree's own depth: trellis wires the
trees are tied to, the posts that carry them, a stake beside each young trunk, irrigation pipes and
support frames. To a segmenter trained on trees alone each of them is a perfect branch (a thin
cylinder near the trunk); the Middlebury Jadeplant pair's blue Lego frame is one. `orchard_hardware`
draws a random set of them for `SynthOptions.orchard_hardware`, as straight cylinders of painted,
galvanised or plastic surfaces (near-uniform colour, no bark furrows), all in the background class
(mask id 0): the network is to learn that straightness at the tree's depth is not enough.

Pieces are given in the scene's world frame (metres, y down), like every other cone of the scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereo.synth.primitives import norm3, unit
from stereo.synth.textures import periodic_noise

#: surface colours (linear RGB albedo in [0, 1]) of orchard hardware: metal, concrete and paint or plastic
HARDWARE_COLOURS: dict[str, tuple[float, float, float]] = {
    "galvanised": (0.55, 0.57, 0.60),
    "concrete": (0.62, 0.61, 0.57),
    "black_plastic": (0.07, 0.07, 0.08),
    "white_plastic": (0.85, 0.85, 0.82),
    "green_coated": (0.12, 0.32, 0.13),
    "blue_paint": (0.10, 0.20, 0.62),
    "red_paint": (0.62, 0.10, 0.08),
    "orange_fibreglass": (0.85, 0.42, 0.08),
    "yellow_paint": (0.85, 0.74, 0.12),
}
#: nothing but a wire comes nearer the camera than this (m): a rod across the lens would hide the whole scene
MIN_RANGE_M = 0.35
#: what each kind of piece may be made of (a wire is steel, a pipe is plastic, …)
_SURFACES = {
    "wire": ("galvanised",),
    "post": ("galvanised", "concrete", "green_coated", "white_plastic"),
    "stake": ("green_coated", "black_plastic", "orange_fibreglass", "yellow_paint", "white_plastic", "galvanised"),
    "rod": tuple(HARDWARE_COLOURS),
}


@dataclass(frozen=True)
class HardwarePiece:
    """One straight cylinder of hardware: from `base` (world, m) along unit `axis` for `length` m, radius
    `radius` m, its surface an RGB tile `S×S×3` in [0, 1] (`surface_tile`)."""

    kind: str
    base: np.ndarray
    axis: np.ndarray
    length: float
    radius: float
    tile: np.ndarray


def surface_tile(rng: np.random.Generator, colour: tuple[float, float, float]) -> np.ndarray:
    """`S×S×3` float32 (the textures' tile size): a near-uniform surface of `colour` with fine grain (±4 %) and faint
    weathering patches (±8 %) — paint, plastic and metal have no furrows, which is what tells them from bark."""
    grain = periodic_noise(rng, 64.0, 64.0, slope=1.5)
    patches = periodic_noise(rng, 3.0, 3.0)
    shade = 1.0 + 0.04 * grain + 0.08 * patches
    base = np.clip(np.array(colour) * rng.uniform(0.85, 1.15), 0.02, 0.95)
    return np.clip(base[None, None, :] * shade[..., None], 0.0, 1.0).astype(np.float32)


def orchard_hardware(
    rng: np.random.Generator,
    trunk_foot: np.ndarray,
    trunk_radius: float,
    ground_y: float,
    right: np.ndarray,
) -> list[HardwarePiece]:
    """Random hardware around a tree whose trunk (radius `trunk_radius` m at the ground) stands at world
    `trunk_foot` (m, its axis) on the ground `ground_y` m below the camera; `right` is the camera's right
    direction in the world (the row runs roughly along it).

    Always 1–4 trellis wires through the trunk's depth; then, each with its own chance, 1–2 posts in the row,
    a stake beside the trunk, and 1–3 rods at any angle within 0.8 m of the trunk (frames, pipes, guards).
    """
    along_row = unit(np.array([right[0], 0.0, right[2]]) + rng.normal(0.0, 0.25, 3) * np.array([1.0, 0.0, 1.0]))
    across_row = np.array([along_row[2], 0.0, -along_row[0]])
    reach = 6.0 + float(np.hypot(trunk_foot[0], trunk_foot[2]))  # wires run past both image edges
    pieces: list[HardwarePiece] = []

    def piece(kind: str, base: np.ndarray, axis: np.ndarray, length: float, radius: float) -> None:
        direction = unit(axis)
        if kind != "wire":  # wires run past the camera by design; anything else stays clear of the lens
            along = base[None, :] + np.linspace(0.0, length, 16)[:, None] * direction[None, :]
            if norm3(along).min() < MIN_RANGE_M + radius:
                return
        surface = HARDWARE_COLOURS[str(rng.choice(_SURFACES[kind]))]
        pieces.append(HardwarePiece(kind, base, direction, float(length), float(radius), surface_tile(rng, surface)))

    height = rng.uniform(0.4, 0.9)
    for _ in range(rng.integers(1, 5)):  # wires at rising heights, just before or behind the trunk
        offset = rng.uniform(-0.12, 0.12) * across_row
        tilt = np.array([0.0, rng.normal(0.0, 0.03), 0.0])
        start = trunk_foot + offset - reach * along_row + np.array([0.0, -height, 0.0])
        piece("wire", start, along_row + tilt, 2 * reach, rng.uniform(0.0012, 0.0025))
        height += rng.uniform(0.3, 0.7)
    if rng.random() < 0.6:
        for _ in range(rng.integers(1, 3)):
            foot = trunk_foot + rng.choice([-1, 1]) * rng.uniform(0.6, 3.0) * along_row
            foot = foot + rng.uniform(-0.1, 0.1) * across_row
            axis = unit(np.array([rng.normal(0, 0.03), -1.0, rng.normal(0, 0.03)]))
            piece("post", foot, axis, height + rng.uniform(0.2, 0.8), rng.uniform(0.03, 0.07))
    if rng.random() < 0.5:
        side = unit(rng.normal(0.0, 1.0, 3) * np.array([1.0, 0.0, 1.0]))
        foot = trunk_foot + (trunk_radius + rng.uniform(0.02, 0.15)) * side  # outside the bark
        axis = unit(np.array([rng.normal(0, 0.05), -1.0, rng.normal(0, 0.05)]))
        piece("stake", foot, axis, rng.uniform(1.2, 2.5), rng.uniform(0.005, 0.014))
    if rng.random() < 0.6:
        for _ in range(rng.integers(1, 4)):
            centre = trunk_foot + np.array(
                [rng.uniform(-0.8, 0.8), -rng.uniform(0.3, min(2.5, ground_y + 1.0)), rng.uniform(-0.8, 0.8)]
            )
            axis = unit(rng.normal(0.0, 1.0, 3))
            length = rng.uniform(0.25, 1.2)
            piece("rod", centre - 0.5 * length * axis, axis, length, rng.uniform(0.004, 0.016))
    return pieces
