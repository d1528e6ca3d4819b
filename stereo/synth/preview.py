"""A picture of synthetic scenes for people: left, right, disparity and instance mask side by side."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from stereo.io import colorize_disparity
from stereo.synth.render import SyntheticScene
from stereo.synth.truth import LEAF_ID, TRUNK_ID, TWIG_ID, is_branch_id

_RESERVED_COLOURS = {TRUNK_ID: (150, 150, 150), TWIG_ID: (110, 80, 60), LEAF_ID: (40, 110, 40)}


def colorize_mask(mask: np.ndarray) -> np.ndarray:
    """RGB `uint8` `H×W×3` of a uint16 instance mask: black background, grey trunk, a bright hue per branch."""
    out = np.zeros((*mask.shape, 3), dtype=np.uint8)
    for value, colour in _RESERVED_COLOURS.items():
        out[mask == value] = colour
    branch = is_branch_id(mask)
    if not branch.any():
        return out
    hues = ((mask[branch].astype(np.int64) * 0.618034) % 1.0 * 180).astype(np.uint8)
    hsv = np.stack([hues, np.full_like(hues, 230), np.full_like(hues, 255)], axis=-1)[None]
    out[branch] = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0]
    return out


def _mark_cut_points(panel: np.ndarray, scene: SyntheticScene) -> np.ndarray:
    """White rings on the truth cut points (filled when the cut point is visible)."""
    panel = panel.copy()
    radius = max(3, panel.shape[1] // 120)
    for branch in scene.branches:
        x, y = (int(round(c)) for c in branch.cut_pixel)
        cv2.circle(panel, (x, y), radius, (255, 255, 255), -1 if branch.cut_visible else 1, lineType=cv2.LINE_AA)
    return panel


def preview_row(scene: SyntheticScene) -> np.ndarray:
    """One scene as RGB `H×4W×3`: left, right, disparity (turbo; black = sky), mask with cut points."""
    disparity = colorize_disparity(scene.disparity)
    mask = _mark_cut_points(colorize_mask(scene.instance_mask), scene)
    return np.concatenate([scene.left, scene.right, disparity, mask], axis=1)


def preview_image(scenes: Sequence[SyntheticScene]) -> np.ndarray:
    """Rows of `preview_row`, one per scene (all scenes must share one size)."""
    if not scenes:
        raise ValueError("preview_image needs at least one scene")
    return np.concatenate([preview_row(scene) for scene in scenes], axis=0)


def contact_sheet(lefts: Sequence[np.ndarray], masks: Sequence[np.ndarray], columns: int = 3) -> np.ndarray:
    """RGB grid of scenes, each its left image (`H×W×3` uint8) beside its coloured instance mask (uint16 `H×W`),
    `columns` scenes a row (a short last row is filled with black); all scenes share one size."""
    if not lefts or len(lefts) != len(masks):
        raise ValueError("contact_sheet needs one mask per left image and at least one scene")
    tiles = [np.concatenate([left, colorize_mask(mask)], axis=1) for left, mask in zip(lefts, masks)]
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    rows = [np.concatenate(tiles[i : i + columns], axis=1) for i in range(0, len(tiles), columns)]
    return np.concatenate(rows, axis=0)
