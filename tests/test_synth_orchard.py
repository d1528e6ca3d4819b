"""The shifted "orchard" domain of the renderer, and rendered truth written as a labelled COCO data set."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from branchrange.learning.samples import LEAF_ID, TRUNK_ID, TWIG_ID
from branchrange.offline.coco_export import BRANCH_CATEGORY, TRUNK_CATEGORY
from branchrange.offline.synth_coco import TRUTH_DIR, export_domain_frames
from stereo.synth import SynthCamera, SynthOptions, render_scene
from stereo.synth.orchard import ORCHARD_BARKS, orchard_bark_tile

CAMERA = SynthCamera.zed_mini(160, 90)
#: SHA-256 over left, right, instance mask and disparity of the default scenes of seeds 5 and 12 at 160×90, as
#: rendered before the domain option existed: the default ("park") must keep drawing exactly these
PARK_DIGESTS = {
    5: "387b2ca976dbc41f27af6079f658eca0bc8c5ee720a9c70ce00e7293e9b01e1a",
    12: "a1d55f9e73bf3e8ba6284d60083c5cfc7cbea87f352118ca9f0da853f98a1cef",
}


def digest(scene) -> str:
    """SHA-256 of a rendered scene's arrays."""
    h = hashlib.sha256()
    for array in (scene.left, scene.right, scene.instance_mask, scene.disparity):
        h.update(array.tobytes())
    return h.hexdigest()


@pytest.mark.parametrize("seed", sorted(PARK_DIGESTS))
def test_the_default_domain_renders_a_seed_bit_for_bit_as_before(seed):
    assert digest(render_scene(seed, CAMERA, threads=1)) == PARK_DIGESTS[seed]
    assert digest(render_scene(seed, CAMERA, threads=1, domain="park")) == PARK_DIGESTS[seed]


def test_the_orchard_renders_another_scene_with_branches_trunk_and_background():
    orchard = render_scene(5, CAMERA, threads=1, domain="orchard")
    assert digest(orchard) != PARK_DIGESTS[5]
    assert len(orchard.branches) >= 2 and (orchard.instance_mask == TRUNK_ID).any()
    assert digest(render_scene(5, CAMERA, threads=1, domain="orchard")) == digest(orchard), "seeded"
    # espalier: the branches run along the row, nearly level — across the image (the camera only rolls ±6°)
    assert np.median([abs(b.direction[0]) for b in orchard.branches]) > 0.8


def test_an_unknown_domain_is_refused():
    with pytest.raises(ValueError, match="domain must be one of"):
        SynthOptions(domain="vineyard")


@pytest.mark.parametrize("kind", sorted(ORCHARD_BARKS))
def test_orchard_barks_are_textured_tiles_in_range(kind):
    tile = orchard_bark_tile(np.random.default_rng(1), kind)
    assert tile.shape == (256, 256, 3) and tile.dtype == np.float32
    assert 0.0 <= tile.min() and tile.max() <= 1.0 and tile.std() > 0.01


def test_rendered_truth_round_trips_through_coco(tmp_path):
    pytest.importorskip("pycocotools")
    from pycocotools.coco import COCO

    from branchrange.learning.samples import evaluation_scene

    seeds = [80_000, 80_001]
    annotations = export_domain_frames(tmp_path, seeds, "orchard", size=(320, 180))
    coco = COCO(str(annotations))
    assert len(coco.getImgIds()) == 2
    for image_id, seed in zip(sorted(coco.getImgIds()), seeds):
        scene = evaluation_scene(seed, None, size=(320, 180), domain="orchard")
        mask = scene["mask"].astype(np.int64)
        read = [coco.annToMask(a).astype(bool) for a in coco.loadAnns(coco.getAnnIds(imgIds=[image_id]))]
        categories = [a["category_id"] for a in coco.loadAnns(coco.getAnnIds(imgIds=[image_id]))]
        branch_ids = sorted(set(np.unique(mask)) - {0, TRUNK_ID, TWIG_ID, LEAF_ID})
        assert categories.count(BRANCH_CATEGORY) == len(branch_ids) and categories.count(TRUNK_CATEGORY) == 1
        truth = [mask == i for i in branch_ids] + [mask == TRUNK_ID]
        for expected, found in zip(truth, read):
            assert np.array_equal(expected, found)
        kept = np.load(tmp_path / TRUTH_DIR / f"frame_{seed:06d}.npz")
        assert np.array_equal(kept["right"], scene["right"])
        assert json.loads(str(kept["truth"])) == scene["truth"]
    # the simulated labelling writes what export-frames writes: train-segmenter --coco reads it as it is
    from branchrange.learning.coco_labels import read_labelled_frames

    labelled = read_labelled_frames(annotations, tmp_path / "images", log=lambda _: None)
    assert [f.name for f in labelled] == [f"frame_{s:06d}.png" for s in seeds]
    assert np.array_equal(
        labelled[0].sample["disparity"], evaluation_scene(seeds[0], None, size=(320, 180), domain="orchard")["sgbm"]
    )
