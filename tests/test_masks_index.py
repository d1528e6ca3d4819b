"""The one-pass instance index and the per-instance crops equal their whole-frame definitions."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from branchrange.core.masks import InstanceIndex, MaskCrop, erode, masks_from_array, split_binary


def random_labels(seed: int, shape=(60, 90), ids=(1, 2, 3, 7, 65535)) -> np.ndarray:
    """Blobs and scattered pixels of a few ids, touching the borders, with holes and split parts."""
    rng = np.random.default_rng(seed)
    labels = np.zeros(shape, np.int32)
    for i in ids:
        for _ in range(rng.integers(1, 4)):
            r, c = rng.integers(0, shape[0]), rng.integers(0, shape[1])
            labels[r : r + rng.integers(1, 20), c : c + rng.integers(1, 30)] = i
    scatter = rng.random(shape) < 0.02
    labels[scatter] = rng.choice(ids, scatter.sum())
    return labels


@pytest.mark.parametrize("seed", range(6))
def test_index_matches_per_id_counts_and_boxes(seed):
    labels = random_labels(seed)
    index = InstanceIndex.of(labels)
    present = np.unique(labels[labels != 0])
    assert index.ids.tolist() == present.tolist()
    for i, count, box in zip(index.ids, index.counts, index.boxes):
        rows, cols = np.nonzero(labels == i)
        assert count == rows.size
        assert box.tolist() == [rows.min(), rows.max() + 1, cols.min(), cols.max() + 1]
    assert index.box(12345) is None


def test_empty_labels_have_no_ids():
    masks = masks_from_array(np.zeros((5, 5), np.uint16), kind="instance")
    assert masks.branch_ids() == [] and masks.trunk() is None and masks.crop(1) is None


@pytest.mark.parametrize("seed", range(4))
def test_crops_give_the_whole_frame_masks_and_pixels(seed):
    labels = random_labels(seed)
    masks = masks_from_array(labels, kind="instance")
    for i in masks.branch_ids():
        whole = labels == i
        crop = masks.crop(i)
        assert np.array_equal(crop.full(), whole) and np.array_equal(masks.branch(i), whole)
        rows, cols = crop.pixels()
        expected = np.nonzero(whole)
        assert np.array_equal(rows, expected[0]) and np.array_equal(cols, expected[1])  # same order
        assert crop.touches_image_border() == bool(
            whole[0].any() or whole[-1].any() or whole[:, 0].any() or whole[:, -1].any()
        )
        assert np.array_equal(crop.with_mask(erode(crop.mask, 1)).full(), erode(whole, 1))
    assert np.array_equal(masks.trunk(), labels == 65535)


def test_a_window_reaching_past_the_image_is_false_outside():
    crop = MaskCrop(np.ones((2, 3), bool), 0, 0, (4, 4))
    window = crop.window(-1, -1, 4, 5)
    assert window.sum() == 6 and window[1:3, 1:4].all()


@pytest.mark.parametrize("seed", range(5))
def test_distances_on_the_window_equal_the_whole_frame_distance_transform(seed):
    rng = np.random.default_rng(seed)
    labels = random_labels(seed, shape=(120, 160))
    trunk = labels == 65535
    whole = cv2.distanceTransform((~trunk).astype(np.uint8), cv2.DIST_L2, 5)
    rows = rng.integers(-5, 125, 40)  # some outside the image: clipped, as the per-frame code did
    cols = rng.integers(-5, 165, 40)
    got = MaskCrop.of(trunk).distances_at(rows, cols)
    assert np.array_equal(got, whole[np.clip(rows, 0, 119), np.clip(cols, 0, 159)])


def test_split_binary_numbers_the_kept_components_in_order():
    mask = np.zeros((10, 20), np.uint8)
    mask[1:3, 1:5] = 255  # 8 px
    mask[5, 8] = 255  # 1 px speckle
    mask[7:9, 12:18] = 255  # 12 px
    labels = split_binary(mask, min_area_px=2)
    assert sorted(np.unique(labels).tolist()) == [0, 1, 2]
    assert (labels == 1).sum() == 8 and (labels == 2).sum() == 12 and labels[5, 8] == 0
