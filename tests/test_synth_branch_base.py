"""The synthetic truth's branch base: exactly where the branch axis leaves the tapered trunk surface."""

from __future__ import annotations

import numpy as np
import pytest

from stereo.synth import TRUNK_ID, SynthCamera, SynthOptions
from stereo.synth.cones import BarkMaterial, Cone
from stereo.synth.scene import build_scene
from stereo.synth.textures import MipTile

CAMERA = SynthCamera.zed_mini(640, 360)
#: Scene 6 holds the three oblique branches whose base used to lie 0.5–0.64 cm off the bark.
SEEDS = (0, 3, 6, 9)
MATERIAL = BarkMaterial(MipTile(np.full((8, 8, 3), 0.5, dtype=np.float32)), 1, 0.1)


def distance_from_axis(cone: Cone, point: np.ndarray) -> tuple[float, float]:
    """(metres along the cone's axis, metres from its axis) of a camera-frame point."""
    rel = point - cone.base
    s = float(rel @ cone.axis)
    return s, float(np.linalg.norm(rel - s * cone.axis))


@pytest.mark.parametrize("seed", SEEDS)
def test_truth_base_lies_on_the_trunk_surface_and_on_the_drawn_branch_axis(seed):
    scene = build_scene(np.random.default_rng(seed), CAMERA, SynthOptions())
    (trunk,) = [c for c in scene.cones if c.instance_id == TRUNK_ID]
    for branch in scene.branches:
        (drawn,) = [c for c in scene.cones if c.instance_id == branch.id]
        base, direction = np.asarray(branch.base_m), np.asarray(branch.direction)
        height, off_axis = distance_from_axis(trunk, base)
        assert off_axis == pytest.approx(trunk.radius_at(height), abs=1e-9), (seed, branch.id)
        along, off_branch_axis = distance_from_axis(drawn, base)
        assert off_branch_axis < 1e-9 and np.allclose(direction, drawn.axis, atol=1e-12)
        # the exit, not the entry on the far side: the axis is inside the bark just before and outside just after
        for step, outside in ((-1e-4, False), (1e-4, True)):
            h, r = distance_from_axis(trunk, base + step * direction)
            assert (r > trunk.radius_at(h)) == outside, (seed, branch.id, step)
        assert np.allclose(branch.cut_point_m, base + SynthOptions().cut_offset_m * direction, atol=1e-12)
        # length and radii still describe the drawn cone: same tip, same taper from the base
        assert np.allclose(branch.tip_m, drawn.base + drawn.length * drawn.axis, atol=1e-12)
        assert branch.base_radius_m == pytest.approx(drawn.radius_at(along), abs=1e-12)
        assert branch.tip_radius_m == pytest.approx(drawn.r1, abs=1e-15)


def test_exit_distance_of_a_line_through_a_tapered_axis_is_the_closed_form():
    # along a line through the axis, distance from it is t·sin θ and the radius R + k·t·cos θ
    cone = Cone(np.array([0.1, 2.0, 3.0]), np.array([0.0, -1.0, 0.0]), 10.0, 0.2, 0.08, MATERIAL, TRUNK_ID)
    k = (cone.r1 - cone.r0) / cone.length
    on_axis = cone.base + 2.5 * cone.axis
    rng = np.random.default_rng(3)
    for _ in range(50):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        cos_t = float(direction @ cone.axis)
        if abs(cos_t) > 0.9:
            continue
        expected = cone.radius_at(2.5) / (np.sqrt(1.0 - cos_t**2) - k * cos_t)
        assert cone.exit_distance(on_axis, direction) == pytest.approx(expected, rel=1e-12)


def test_exit_distance_from_an_off_axis_point_of_a_straight_cylinder_is_the_chord():
    cylinder = Cone(np.zeros(3), np.array([0.0, 0.0, 1.0]), 4.0, 0.5, 0.5, MATERIAL, TRUNK_ID)
    origin = np.array([0.3, 0.0, 1.0])
    assert cylinder.exit_distance(origin, np.array([1.0, 0.0, 0.0])) == pytest.approx(0.2, abs=1e-15)
    assert cylinder.exit_distance(origin, np.array([-1.0, 0.0, 0.0])) == pytest.approx(0.8, abs=1e-15)
    assert cylinder.exit_distance(origin, np.array([0.0, 1.0, 0.0])) == pytest.approx(0.4, abs=1e-15)


def test_exit_distance_rejects_an_origin_outside_and_rays_that_leave_by_no_side():
    cylinder = Cone(np.zeros(3), np.array([0.0, 0.0, 1.0]), 4.0, 0.5, 0.5, MATERIAL, TRUNK_ID)
    with pytest.raises(ValueError, match=r"origin \[0.6, 0.0, 1.0\] is not inside"):
        cylinder.exit_distance(np.array([0.6, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="never leaves the side surface"):
        cylinder.exit_distance(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]))
    slanted = np.array([0.1, 0.0, 1.0]) / np.linalg.norm([0.1, 0.0, 1.0])
    with pytest.raises(ValueError, match="through an end"):
        cylinder.exit_distance(np.array([0.0, 0.0, 3.9]), slanted)
