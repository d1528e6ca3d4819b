"""Orchard hardware in synthetic scenes: background, in front of the tree, and nothing else changes."""

from __future__ import annotations

import numpy as np
import pytest

from stereo.synth import SynthCamera, SynthOptions, render_scene
from stereo.synth.hardware import HARDWARE_COLOURS, MIN_RANGE_M, orchard_hardware, surface_tile
from stereo.synth.primitives import norm3
from stereo.synth.scene import build_scene

CAMERA = SynthCamera.zed_mini(320, 180)


def test_hardware_is_background_in_front_of_the_same_tree():
    plain = render_scene(3001, CAMERA, supersample=1)
    with_hardware = render_scene(3001, CAMERA, supersample=1, orchard_hardware=True)
    assert with_hardware.branches == plain.branches  # the tree and its truth are drawn before the hardware
    nearer = with_hardware.depth_m < plain.depth_m - 0.05
    assert nearer.sum() > 50, "the wires, posts, stakes and rods hide part of the scene"
    assert np.all(with_hardware.instance_mask[nearer] == 0), "hardware is background, never a branch or the trunk"
    assert not np.any(with_hardware.depth_m > plain.depth_m + 1e-4), "hardware only adds surfaces"


def test_without_the_option_a_seeds_scene_is_what_it_was():
    default = build_scene(np.random.default_rng(7), CAMERA, SynthOptions())
    off = build_scene(np.random.default_rng(7), CAMERA, SynthOptions(orchard_hardware=False))
    on = build_scene(np.random.default_rng(7), CAMERA, SynthOptions(orchard_hardware=True))
    assert len(default.cones) == len(off.cones) < len(on.cones)
    assert default.exposure_target == off.exposure_target == on.exposure_target


@pytest.mark.parametrize("seed", range(20))
def test_every_run_has_a_wire_and_nothing_comes_near_the_lens(seed):
    rng = np.random.default_rng(seed)
    foot = np.array([rng.uniform(-1, 1), rng.uniform(1.0, 2.5), rng.uniform(0.5, 3.0)])
    pieces = orchard_hardware(rng, foot, 0.15, float(foot[1]), np.array([1.0, 0.0, 0.0]))
    assert any(p.kind == "wire" for p in pieces)
    for p in pieces:
        assert np.isclose(np.linalg.norm(p.axis), 1.0) and p.length > 0 and 0 < p.radius < 0.08
        along = p.base[None, :] + np.linspace(0, p.length, 16)[:, None] * p.axis[None, :]
        if p.kind != "wire":
            assert norm3(along).min() >= MIN_RANGE_M
        if p.kind == "stake":  # beside the trunk, outside its bark
            assert 0.15 + 0.02 <= np.hypot(*(p.base - foot)[[0, 2]]) <= 0.15 + 0.15


def test_surfaces_are_near_uniform_unlike_bark():
    rng = np.random.default_rng(0)
    for colour in HARDWARE_COLOURS.values():
        tile = surface_tile(rng, colour)
        assert tile.shape[2] == 3 and tile.min() >= 0 and tile.max() <= 1
        luminance = tile.mean(axis=2)
        assert luminance.std() / luminance.mean() < 0.15
