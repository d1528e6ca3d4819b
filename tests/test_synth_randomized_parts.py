"""Parts of the randomized generator: grown skeletons, bark, camera effects and disparity dropout."""

from __future__ import annotations

import numpy as np
import pytest

from stereo.synth import bark
from stereo.synth import camera_effects as effects
from stereo.synth.cones import BarkMaterial, Cone
from stereo.synth.growth import FORM_NAMES, FORMS, Skeleton, grow_tree
from stereo.synth.planes import PlaneLayer
from stereo.synth.primitives import Lighting
from stereo.synth.randomized import BranchLabels, near_row_ids
from stereo.synth.shadows import ShadowedPlane, cast_on_ground
from stereo.synth.stereo_effects import Dropout, dropped_out
from stereo.synth.textures import MipTile
from stereo.synth.truth import TRUNK_ID, TWIG_ID


@pytest.mark.parametrize("form", FORM_NAMES)
def test_every_form_grows_a_tree_with_pipe_model_radii(form):
    skeleton = grow_tree(np.random.default_rng(11), form)
    assert len(skeleton.start) > 10 and skeleton.tip.any()
    low, high = FORMS[form].trunk_radius_m
    assert low <= skeleton.r0.max() <= high + 1e-9, "the trunk's foot gets the radius drawn for the form"
    assert np.all(skeleton.r1 <= skeleton.r0 + 1e-12), "wood never thickens toward the tips"
    assert (skeleton.order == 0).any() and (skeleton.order == 1).any()
    root = skeleton.first_order_root
    assert np.all(root[skeleton.order == 0] == -1) and np.all(root[skeleton.order >= 1] >= 0)
    assert -skeleton.end[:, 1].min() <= FORMS[form].height_m[1] * 1.3, "the tree stays about its height"


def test_a_tree_is_a_function_of_its_seed():
    a, b = (grow_tree(np.random.default_rng(5), "vase") for _ in range(2))
    c = grow_tree(np.random.default_rng(6), "vase")
    assert np.array_equal(a.end, b.end) and np.array_equal(a.r0, b.r0)
    assert len(a.end) != len(c.end) or not np.array_equal(a.end, c.end)


def test_unknown_form_is_named():
    with pytest.raises(ValueError, match="unknown tree form 'baobab'"):
        grow_tree(np.random.default_rng(0), "baobab")


def test_bark_looks_range_widely_and_young_wood_differs():
    looks = [bark.draw_look(np.random.default_rng(seed)) for seed in range(40)]
    colours = np.array([look.colour for look in looks])
    assert colours.mean(axis=1).max() - colours.mean(axis=1).min() > 0.25
    assert any(look.moss > 0 for look in looks) and any(look.wet for look in looks)
    look = looks[0]
    old = bark.old_wood_tile(np.random.default_rng(1), look)
    young = bark.young_wood_tile(np.random.default_rng(1), look)
    assert old.shape == young.shape == (256, 256, 3) and 0 <= old.min() and old.max() <= 1
    assert not np.allclose(old.mean(axis=(0, 1)), young.mean(axis=(0, 1)), atol=0.01)


def _picture() -> np.ndarray:
    """A smooth 90×160 gradient with a few edges, uint8 RGB."""
    y, x = np.mgrid[0:90, 0:160]
    image = np.stack([x * 1.5, y * 2.5, (x + y) % 64 * 3], axis=2)
    return np.clip(image, 0, 255).astype(np.uint8)


def test_compression_leaves_its_artefacts_and_more_with_coarser_steps():
    image = _picture()
    fine, coarse = effects.h264_like(image, 2.0), effects.h264_like(image, 30.0)
    error = [np.abs(out.astype(int) - image).mean() for out in (fine, coarse)]
    assert 0 < error[0] < error[1]
    low, high = effects.jpeg_compressed(image, 20), effects.jpeg_compressed(image, 95)
    assert np.abs(low.astype(int) - image).mean() > np.abs(high.astype(int) - image).mean()


def test_noise_grows_with_gain_and_level():
    image = np.full((64, 64, 3), 0.3, dtype=np.float32)
    rng = np.random.default_rng(0)
    weak = effects.noisy(image, rng, 1.0, 0.1, 1.0).std()
    strong = effects.noisy(image, rng, 1.0, 0.1, 4.0).std()
    assert 0 < weak < strong


def test_vignetting_darkens_corners_and_defocus_blurs_off_the_focus():
    image = np.ones((90, 160, 3), dtype=np.float32)
    dark = effects.vignetted(image, 0.4)
    assert dark[45, 80, 0] > 0.99 and dark[0, 0, 0] == pytest.approx(0.6, abs=0.01)
    stripes = np.zeros((90, 160, 3), dtype=np.float32)
    stripes[:, ::4] = 1.0
    depth = np.full((90, 160), 1.0)
    assert np.array_equal(effects.defocused(stripes, depth, 1.0, 3.0), stripes), "in focus stays sharp"
    assert effects.defocused(stripes, depth * 10, 1.0, 3.0).std() < 0.5 * stripes.std()


def test_dropout_blanks_the_frame_or_regions():
    disparity = np.full((90, 160), 12.0, dtype=np.float32)
    rng = np.random.default_rng(0)
    assert not dropped_out(disparity, rng, "frame", Dropout()).any()
    regions = dropped_out(disparity, rng, "regions", Dropout())
    assert 0 < (regions == 0).mean() < 1
    assert np.array_equal(dropped_out(disparity, rng, "none", Dropout()), disparity)


def test_a_pole_casts_a_shadow_as_long_as_the_sun_is_low():
    ground = PlaneLayer(
        np.array([0.0, 1.5, 0.0]), np.array([1.0, 0, 0]), np.array([0.0, 0, 1.0]), MipTile(np.ones((8, 8, 3))), 1.0, 1.0
    )  # the ground 1.5 m below a level camera (y down); its normal points up
    material = BarkMaterial(MipTile(np.ones((8, 8, 3))), 1, 0.3)
    pole = Cone(np.array([0.0, 1.5, 5.0]), np.array([0.0, -1.0, 0.0]), 2.0, 0.05, 0.05, material, 0)
    elevation = np.radians(30.0)
    sun = np.array([0.0, -np.sin(elevation), np.cos(elevation)])  # ahead of the camera, 30° up
    shadow = cast_on_ground([pole], ground, sun)
    along = np.linspace(0.0, 5.0, 101)  # from the pole's foot toward the camera (away from the sun)
    coverage = shadow.at(np.zeros_like(along), 5.0 - along)  # plane coordinates: u = x, v = z
    length = along[coverage > 0.5].max()
    assert length == pytest.approx(2.0 / np.tan(elevation), abs=0.1)
    assert shadow.at(np.array([1.0]), np.array([4.0]))[0] == 0.0, "beside the shadow, sunlit"
    assert cast_on_ground([pole], ground, np.array([0.0, 0.1, 1.0]) / np.hypot(0.1, 1.0)) is None, "sun below horizon"
    light = Lighting(sun, np.ones(3), np.full(3, 0.25), np.ones(3), 1e9)
    shaded = ShadowedPlane.of(ground, shadow)
    points = np.array([[0.0, 1.5, 4.0], [1.0, 1.5, 4.0]])  # in the shadow, then beside it
    colour = shaded.shade(points, np.zeros(2, dtype=np.int64), light, 1e-3)
    assert colour[0, 0] == pytest.approx(0.25, abs=0.02) and colour[1, 0] == pytest.approx(1.25, abs=0.02)


def test_near_row_labels_a_branch_within_4_m_and_its_shoots_but_not_one_beyond():
    start = np.array([[0, 0, 1], [0, -1, 1], [0.5, -1, 1], [0, -1, 6], [0.5, -1, 6]], dtype=float)
    end = np.array([[0, -1, 1], [0.5, -1, 1], [0.6, -1.1, 1], [0.5, -1, 6], [0.6, -1.1, 6]], dtype=float)
    skeleton = Skeleton(
        "central_leader",
        start,
        end,
        np.full(5, 0.02),
        np.full(5, 0.01),
        order=np.array([0, 1, 2, 1, 2]),
        axis_id=np.array([0, 1, 2, 3, 4]),
        axis_parent=np.array([-1, 0, 1, 0, 3]),
        tip=np.array([False, False, True, False, True]),
    )
    ids = near_row_ids(skeleton, start, end, BranchLabels())
    assert ids.tolist() == [TRUNK_ID, 1, TWIG_ID, 0, 0]
