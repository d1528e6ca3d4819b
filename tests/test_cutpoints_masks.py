"""Instance masks: 8/16-bit PNGs, binary masks split into components, validation errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from branchrange.core.masks import MaskError, erode, masks_from_array, read_mask, validate_masks, write_instance_mask


def two_branches_and_trunk(trunk_id: int) -> np.ndarray:
    labels = np.zeros((40, 60), dtype=np.int32)
    labels[5:8, 10:50] = 1
    labels[20:23, 10:50] = 2
    labels[:, 55:59] = trunk_id
    return labels


def test_sixteen_bit_png_keeps_ids_and_trunk(tmp_path):
    labels = two_branches_and_trunk(65535)
    path = write_instance_mask(tmp_path / "m.png", labels)
    assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    masks = read_mask(path, trunk_id=65535)
    assert masks.branch_ids() == [1, 2]
    assert masks.trunk().sum() == 40 * 4


def test_eight_bit_png_with_configured_trunk_id(tmp_path):
    path = write_instance_mask(tmp_path / "m.png", two_branches_and_trunk(200))
    assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED).dtype == np.uint8
    masks = read_mask(path, trunk_id=200)
    assert masks.branch_ids() == [1, 2] and masks.trunk() is not None
    # without knowing the trunk id, the trunk is just another instance
    assert read_mask(path, trunk_id=None).branch_ids() == [1, 2, 200]


def test_binary_mask_splits_into_connected_components(tmp_path):
    binary = (two_branches_and_trunk(1) > 0).astype(np.uint8) * 255
    path = tmp_path / "b.png"
    cv2.imwrite(str(path), binary)
    masks = read_mask(path)
    assert len(masks.branch_ids()) == 3 and masks.trunk() is None
    sizes = sorted(int(masks.branch(i).sum()) for i in masks.branch_ids())
    assert sizes == [120, 120, 160]


def test_boolean_array_is_binary():
    masks = masks_from_array(two_branches_and_trunk(1) == 1)  # branch 1 and the trunk, not touching
    assert masks.branch_ids() == [1, 2]
    assert sorted(int(masks.branch(i).sum()) for i in (1, 2)) == [120, 160]


def test_missing_and_undecodable_mask_files_name_the_path(tmp_path):
    with pytest.raises(MaskError, match="nope.png does not exist"):
        read_mask(tmp_path / "nope.png")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png")
    with pytest.raises(MaskError, match="bad.png could not be decoded"):
        read_mask(bad)


def test_wrong_size_mask_is_rejected_with_both_sizes():
    masks = masks_from_array(two_branches_and_trunk(255))
    with pytest.raises(MaskError, match=r"60×40 .* 64×48"):
        validate_masks(masks, (48, 64, 3))


def test_negative_and_fractional_ids_are_rejected():
    with pytest.raises(MaskError, match="≥ 0"):
        masks_from_array(np.full((4, 4), -1))
    with pytest.raises(MaskError, match="whole numbers"):
        masks_from_array(np.full((4, 4), 0.5))


def test_erosion_shrinks_but_never_erases():
    mask = np.zeros((20, 20), dtype=bool)
    mask[5:15, 5:15] = True
    assert erode(mask, 1).sum() == 64
    thin = np.zeros((20, 20), dtype=bool)
    thin[10, 2:18] = True
    assert erode(thin, 1).sum() == thin.sum()


def test_reserved_twig_and_leaf_ids_are_neither_branch_nor_trunk():
    labels = two_branches_and_trunk(65535)
    labels[30:32, 0:5] = 65534
    labels[35:37, 0:5] = 65533
    masks = masks_from_array(labels.astype(np.uint16))
    assert masks.branch_ids() == [1, 2]
    assert masks_from_array(labels.astype(np.uint16), ignored_ids=()).branch_ids() == [1, 2, 65533, 65534]
