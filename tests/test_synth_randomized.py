"""The randomized scene generator: every factor seedable and switchable, labels exact, the training format kept."""

from __future__ import annotations

import dataclasses
import json
from functools import lru_cache

import numpy as np
import pytest

from branchrange.learning.samples import render_randomized_sample
from stereo.cli import main as emcstereo
from stereo.io import read_rgb
from stereo.synth import SynthCamera
from stereo.synth.randomized import (
    RandomizedSample,
    RandomizedSwitches,
    draw_plan,
    render_randomized,
    switch_names,
)
from stereo.synth.truth import LEAF_ID, TRUNK_ID, TWIG_ID, is_branch_id

CAMERA = SynthCamera.zed_mini(160, 90)
NEUTRAL = RandomizedSwitches.only()


@lru_cache(maxsize=64)
def rendered(seed: int, switches: RandomizedSwitches) -> RandomizedSample:
    """One small render per (seed, switches), shared by the tests."""
    return render_randomized(seed, CAMERA, switches, supersample=1)


def seeds_changing(factor: str) -> list[int]:
    """Seeds in 0..99 whose plan with only `factor` on differs from the neutral plan (a categorical factor may
    draw its neutral value: season 'dormant', light 'sun')."""
    only = RandomizedSwitches.only(factor)
    return [
        seed
        for seed in range(100)
        if dataclasses.replace(draw_plan(seed, only), seed=0) != dataclasses.replace(draw_plan(seed, NEUTRAL), seed=0)
    ]


def first_seed_changing(factor: str) -> int:
    """The first of `seeds_changing`."""
    seeds = seeds_changing(factor)
    assert seeds, f"no seed in 0..99 draws {factor} away from its neutral value"
    return seeds[0]


def same(a: RandomizedSample, b: RandomizedSample) -> bool:
    """Byte-identical images, disparity and labels."""
    return all(
        np.array_equal(getattr(a, name), getattr(b, name))
        for name in ("left", "right", "disparity", "exact_disparity", "instances")
    )


@pytest.mark.parametrize("factor", switch_names())
def test_each_factor_is_seedable_and_its_switch_changes_the_scene(factor):
    only = RandomizedSwitches.only(factor)
    seed = first_seed_changing(factor)
    assert same(rendered(seed, only), render_randomized(seed, CAMERA, only, supersample=1)), (
        f"{factor}: the same seed must render the same bytes"
    )
    if factor == "dropout":
        changed, neutral = rendered(seed, only), rendered(seed, NEUTRAL)
        assert (changed.disparity == 0).sum() > (neutral.disparity == 0).sum()
        assert np.array_equal(changed.left, neutral.left), "dropout touches the disparity only"
        return
    # what a factor changes may be out of view (the ground of a camera looking up): one of a few seeds must show it
    shown = [
        s for s in seeds_changing(factor)[:4] if not np.array_equal(rendered(s, only).left, rendered(s, NEUTRAL).left)
    ]
    assert shown, f"switching {factor} on must change the image"


def test_every_factor_on_is_deterministic_and_seeds_differ():
    switches = RandomizedSwitches()
    first = render_randomized(7, CAMERA, switches, supersample=1)
    assert same(first, render_randomized(7, CAMERA, switches, supersample=1))
    assert not np.array_equal(first.left, rendered(8, switches).left)


def test_switching_one_factor_leaves_the_others_draws_alone():
    all_on = draw_plan(3, RandomizedSwitches())
    no_season = draw_plan(3, dataclasses.replace(RandomizedSwitches(), season=False))
    assert no_season.season == "dormant"
    assert dataclasses.replace(no_season, season=all_on.season) == all_on


def test_near_tree_is_labelled_trunk_branches_and_twigs():
    sample = rendered(2, NEUTRAL)
    ids = sample.instances
    assert (ids == TRUNK_ID).sum() > 20
    branch_ids = np.unique(ids[is_branch_id(ids)])
    assert branch_ids.size >= 2, "first-order branches of the near tree each get an instance id"
    assert set(np.unique(ids)) <= {0, TRUNK_ID, TWIG_ID, *branch_ids.tolist()}, "no leaves when dormant"


@pytest.mark.parametrize("factor", ["rows_behind", "structures", "backdrop"])
def test_what_stands_behind_and_around_is_background(factor):
    seed = first_seed_changing(factor)
    neutral, added = rendered(seed, NEUTRAL), rendered(seed, RandomizedSwitches.only(factor))
    nearer = added.exact_disparity > neutral.exact_disparity + 1e-3
    assert nearer.sum() > 10, f"{factor} adds surfaces in front of what was there"
    assert np.all(added.instances[nearer] == 0), f"{factor} is background, never wood of the near row"
    untouched = ~nearer
    assert np.array_equal(added.instances[untouched & (neutral.instances > 0)], neutral.instances[untouched &
                          (neutral.instances > 0)]), "the near tree keeps its labels"  # fmt: skip


def test_leaves_and_blossom_are_leaves_not_wood():
    seed = next(s for s in range(100) if draw_plan(s, RandomizedSwitches.only("season")).season == "blossom")
    ids = rendered(seed, RandomizedSwitches.only("season")).instances
    assert (ids == LEAF_ID).sum() > 0


def test_training_sample_keeps_the_learning_samples_format():
    sample = render_randomized_sample(4, (160, 90))
    assert set(sample) == {"left", "disparity", "classes", "instances"}
    assert sample["left"].dtype == np.uint8 and sample["left"].shape == (90, 160, 3)
    assert sample["disparity"].dtype == np.float16 and sample["disparity"].shape == (90, 160)
    assert sample["classes"].dtype == np.uint8 and sample["instances"].dtype == np.uint16
    assert set(np.unique(sample["classes"])) <= {0, 1, 2, 255}


def test_bad_switches_are_refused_with_the_name():
    with pytest.raises(ValueError, match="unknown factor"):
        RandomizedSwitches.only("weather")
    with pytest.raises(ValueError, match="rows_behind_m"):
        RandomizedSwitches(rows_behind_m=(20.0, 10.0))


def test_synth_command_writes_randomized_samples_and_a_contact_sheet(tmp_path, capsys):
    sheet = tmp_path / "sheet.png"
    out = tmp_path / "randomized"
    status = emcstereo(
        [
            "synth",
            "--randomized",
            "--out",
            str(out),
            "--scenes",
            "2",
            "--seed",
            "5",
            "--size",
            "96x64",
            "--supersample",
            "1",
            "--preview",
            str(sheet),
        ]  # fmt: skip
    )
    assert status == 0
    assert "wrote 2 randomized scenes" in capsys.readouterr().out
    with np.load(out / "randomized_6.npz") as saved:
        again = render_randomized(6, SynthCamera.zed_mini(96, 64), RandomizedSwitches(), supersample=1)
        assert np.array_equal(saved["left"], again.left) and np.array_equal(saved["instances"], again.instances)
    assert json.loads((out / "randomized_5.json").read_text())["seed"] == 5
    assert read_rgb(sheet).shape == (64, 3 * 2 * 96, 3)


def test_synth_command_names_a_bad_randomized_flag(tmp_path):
    with pytest.raises(SystemExit, match="--supersample must be 1 to 4"):
        emcstereo(["synth", "--randomized", "--preview", str(tmp_path / "s.png"), "--supersample", "9"])
    with pytest.raises(SystemExit, match="give --out DIR"):
        emcstereo(["synth", "--randomized"])


def test_a_ground_robots_view_stands_back_from_the_tree_with_the_ground_in_front():
    switches = RandomizedSwitches.only("viewpoint")
    seeds = seeds_changing("viewpoint")
    assert all(draw_plan(s, switches).viewpoint == "ground" for s in seeds)
    assert 0.2 < len(seeds) / 100 < 0.5  # `ground_view_share` of the scenes, 0.35
    ground, crown = rendered(seeds[0], switches), rendered(seeds[0], NEUTRAL)
    wood = ground.instances > 0
    depth_m = CAMERA.focal_px * CAMERA.baseline_m / np.median(ground.exact_disparity[wood])
    low, high = switches.ground_view_m
    assert low <= depth_m <= high + 1.0  # the near tree, its trunk's radius and slant beyond `ground_view_m`
    assert np.count_nonzero(wood) < np.count_nonzero(crown.instances > 0)  # the same tree, smaller in view
    with pytest.raises(ValueError, match="ground_view_share must lie in 0–1"):
        RandomizedSwitches(ground_view_share=1.5)
