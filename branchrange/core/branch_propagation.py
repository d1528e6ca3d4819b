"""Carry a frame's branch masks to the next frame without the segmenter: one image alignment per branch.

A tree does not change between two frames 67 ms apart; the camera moves a little. So between keyframes
(`[roi] keyframe_interval_s`) each branch's mask is moved to where its own pixels went: its
bounding box of the previous rectified left image, weighted by the (slightly grown) mask, is matched
in the new image within `track_search_px` (`cv2.matchTemplate`, normalised cross-correlation with the
mask: a mean-subtracted score in [-1, 1] that only the branch's pixels and a thin rim decide, so the
background's parallax does not pull it). The best score is the photometric check: under
`track_min_ncc` the branch is lost (its pixels went somewhere the image cannot say). The trunk moves by
the branches' median shift (it is only used at coarse resolution). What the new frame's fine disparity
supports of each moved mask is the second check (`verify_support`).

Pixels are (u, v) = (column, row); labels are `int32 H×W` instance ids as in `branchrange.core.masks`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from branchrange.core.masks import BranchMasks, MaskCrop

#: Growth (px) of a branch's mask before matching: its silhouette's edge pixels and a thin rim of
#: background carry most of the texture of a thin stem.
TEMPLATE_GROWTH_PX = 2
#: The trunk is matched at this many times less resolution (the coarse pass's scale at HD720).
TRUNK_MATCH_SCALE = 2


@dataclass(frozen=True)
class Propagation:
    """An anchor frame's labels carried to a new frame: `labels` (`int32 H×W`), each kept branch's (du, dv)
    shift (px, whole: where its mask was placed), its match score, the branches that were `lost` (left out
    of `labels`), and `offsets`: each kept branch's and the trunk's shift from the anchor to the sub-pixel
    (px, float), to centre the next frame's search on."""

    labels: np.ndarray
    shifts: dict[int, tuple[int, int]]
    scores: dict[int, float]
    lost: tuple[int, ...]
    offsets: dict[int, tuple[float, float]] = field(default_factory=dict)


def _paste(labels: np.ndarray, crop: np.ndarray, row0: int, col0: int, value: int, only_empty: bool = False) -> None:
    """Write `value` into `labels` (`int32 H×W`, in place) where the boolean `crop`, placed with its top-left
    pixel at (`row0`, `col0`), is set; what falls outside the image is cut."""
    height, width = labels.shape
    r0, c0 = max(0, row0), max(0, col0)
    r1, c1 = min(height, row0 + crop.shape[0]), min(width, col0 + crop.shape[1])
    if r0 >= r1 or c0 >= c1:
        return
    piece = crop[r0 - row0 : r1 - row0, c0 - col0 : c1 - col0]
    target = labels[r0:r1, c0:c1]
    if only_empty:
        piece = piece & (target == 0)
    target[piece] = value


def _kept_at_borders(
    mask: np.ndarray, row0: int, col0: int, shift: tuple[int, int], image_shape: tuple[int, int]
) -> tuple[np.ndarray, int, int]:
    """A branch's boolean crop `mask` (top-left at `row0`, `col0`) moved by `shift` = (du, dv), and still
    reaching every image edge it reached before: a silhouette the border cut continues out of view, and
    moved away from the border its cut end must not look like a real end (a cut point would be placed
    there: `branch_base`). The edge row or column is repeated into the gap. Returns (crop, row0, col0)
    of the moved crop."""
    height, width = image_shape
    du, dv = shift
    row0, col0 = row0 + dv, col0 + du
    if dv < 0 and row0 - dv + mask.shape[0] == height and mask[-1].any():  # touched the bottom, moved up
        mask = np.vstack([mask, np.repeat(mask[-1:], -dv, axis=0)])
    if dv > 0 and row0 - dv == 0 and mask[0].any():  # touched the top, moved down
        mask, row0 = np.vstack([np.repeat(mask[:1], dv, axis=0), mask]), row0 - dv
    if du < 0 and col0 - du + mask.shape[1] == width and mask[:, -1].any():  # touched the right edge, moved left
        mask = np.hstack([mask, np.repeat(mask[:, -1:], -du, axis=1)])
    if du > 0 and col0 - du == 0 and mask[:, 0].any():  # touched the left edge, moved right
        mask, col0 = np.hstack([np.repeat(mask[:, :1], du, axis=1), mask]), col0 - du
    return mask, row0, col0


def _match(
    previous: np.ndarray,
    current: np.ndarray,
    weight: np.ndarray,
    box: tuple[int, int, int, int],
    search_px: int,
    around: tuple[float, float] = (0.0, 0.0),
) -> tuple[tuple[float, float], float]:
    """((du, dv) px to the sub-pixel, score) of the template `previous[box]` (`box` = row0, row1, col0, col1)
    found in `current` (both `uint8 H×W` grey) within `search_px` of the shift `around` (px), weighted by the
    boolean `weight` (the box's size); score −1 when nothing can be matched (a flat template, no room to
    search). The sub-pixel part is the vertex of a parabola through the best score and its neighbours: a
    track anchored on its keyframe is placed from the sum of whole pixels otherwise, and their rounding
    would move it."""
    height, width = previous.shape
    row0, row1, col0, col1 = box
    du0, dv0 = int(round(around[0])), int(round(around[1]))
    template = previous[row0:row1, col0:col1]
    top, left = max(0, row0 + dv0 - search_px), max(0, col0 + du0 - search_px)
    bottom, right = min(height, row1 + dv0 + search_px), min(width, col1 + du0 + search_px)
    if bottom - top < template.shape[0] or right - left < template.shape[1] or not weight.any():
        return (0.0, 0.0), -1.0
    window = current[top:bottom, left:right]
    scores = cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED, mask=weight.astype(np.uint8) * 255)
    scores = np.nan_to_num(scores, nan=-1.0, posinf=-1.0, neginf=-1.0)
    _, best, _, (u, v) = cv2.minMaxLoc(scores)
    fu = _vertex(scores[v, u - 1 : u + 2]) if 0 < u < scores.shape[1] - 1 else 0.0
    fv = _vertex(scores[v - 1 : v + 2, u]) if 0 < v < scores.shape[0] - 1 else 0.0
    return (left + u + fu - col0, top + v + fv - row0), float(best)


def _vertex(three: np.ndarray) -> float:
    """Where (in [−½, ½] px from the middle) the parabola through three scores peaks."""
    curvature = float(three[0] - 2.0 * three[1] + three[2])
    if curvature >= 0:
        return 0.0
    return float(np.clip(0.5 * float(three[0] - three[2]) / curvature, -0.5, 0.5))


def propagate_labels(
    previous_grey: np.ndarray,
    previous: BranchMasks,
    grey: np.ndarray,
    *,
    search_px: int,
    min_ncc: float,
    offsets: dict[int, tuple[float, float]] | None = None,
) -> Propagation:
    """Carry the instances `previous` (on `previous_grey`, the anchor) to the frame `grey` (both `uint8 H×W`).

    Each branch is matched on its own, from its bounding box (the work follows the branches' pixels, not
    the frame's), within `search_px` of its `offsets` (px from the anchor where the last frame found it; none:
    where it was); one scoring under `min_ncc` is lost. Anchoring every frame between two keyframes on the
    keyframe itself (its image and masks) keeps each mask its own shape: matched from frame to frame,
    a template drifts a little each time and the errors add up (~0.3 cm a frame in the cut points).
    The trunk is matched on its own too (`_trunk_shift`).
    """
    offsets = offsets or {}
    height, width = previous.shape
    labels = np.zeros((height, width), np.int32)
    shifts: dict[int, tuple[int, int]] = {}
    found: dict[int, tuple[float, float]] = {}
    scores: dict[int, float] = {}
    lost: list[int] = []
    grow = TEMPLATE_GROWTH_PX
    kernel = np.ones((2 * grow + 1,) * 2, np.uint8)
    for branch_id in previous.branch_ids():
        row0, row1, col0, col1 = previous.index.box(branch_id)  # type: ignore[misc]  # ids come from the index
        box = (max(0, row0 - grow), min(height, row1 + grow), max(0, col0 - grow), min(width, col1 + grow))
        mask = previous.labels[box[0] : box[1], box[2] : box[3]] == branch_id
        weight = cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)
        offset, score = _match(previous_grey, grey, weight, box, search_px, offsets.get(branch_id, (0.0, 0.0)))
        scores[branch_id] = score
        if score < min_ncc:
            lost.append(branch_id)
            continue
        found[branch_id] = offset
        shifts[branch_id] = shift = (int(round(offset[0])), int(round(offset[1])))
        _paste(labels, *_kept_at_borders(mask, box[0], box[2], shift, (height, width)), branch_id)
    trunk = previous.trunk_crop(margin=0)
    if trunk is not None and previous.trunk_id is not None and shifts:
        last = offsets.get(previous.trunk_id)
        trunk_offset = _trunk_shift(previous_grey, grey, trunk, search_px, min_ncc, found, last)
        found[previous.trunk_id] = trunk_offset
        du, dv = int(round(trunk_offset[0])), int(round(trunk_offset[1]))
        _paste(labels, trunk.mask, trunk.top + dv, trunk.left + du, int(previous.trunk_id), only_empty=True)
    return Propagation(labels, shifts, scores, tuple(lost), found)


def _trunk_shift(
    previous_grey: np.ndarray,
    grey: np.ndarray,
    trunk: MaskCrop,
    search_px: int,
    min_ncc: float,
    branch_offsets: dict[int, tuple[float, float]],
    around: tuple[float, float] | None,
) -> tuple[float, float]:
    """(du, dv) px of the trunk between the two `uint8 H×W` grey frames, searched around `around` (its last
    shift; None: the branches' median): its own pixels matched at `TRUNK_MATCH_SCALE` times less resolution
    (it is large, a frame's height near the tree, and its cylinder is fitted on the coarse pass anyway).
    The trunk stands at its own depth, so the branches' shifts are not its own (parallax: their median put
    it 2–4 px off at 2–3 m, the cylinder's axis ~1 cm, and every branch's base with it); their median only
    when its own match fails."""
    median = tuple(float(np.median(axis)) for axis in zip(*branch_offsets.values()))
    start = median if around is None else around
    factor = TRUNK_MATCH_SCALE
    small = (grey.shape[1] // factor, grey.shape[0] // factor)
    before = cv2.resize(previous_grey, small, interpolation=cv2.INTER_AREA)
    after = cv2.resize(grey, small, interpolation=cv2.INTER_AREA)
    rows, cols = trunk.pixels()
    coarse = np.zeros(before.shape, bool)
    coarse[np.minimum(rows // factor, small[1] - 1), np.minimum(cols // factor, small[0] - 1)] = True
    r, c = np.flatnonzero(coarse.any(axis=1)), np.flatnonzero(coarse.any(axis=0))
    box = (int(r[0]), int(r[-1]) + 1, int(c[0]), int(c[-1]) + 1)
    weight = coarse[box[0] : box[1], box[2] : box[3]]
    around_small = (start[0] / factor, start[1] / factor)
    (du, dv), score = _match(before, after, weight, box, max(1, search_px // factor), around_small)
    if score >= min_ncc:
        return du * factor, dv * factor
    return median[0], median[1]


def verify_support(
    moved: np.ndarray, refined: np.ndarray, branch_ids: list[int], min_support: float
) -> tuple[np.ndarray, tuple[int, ...]]:
    """The refined labels (`int32 H×W`) without the branches the new frame's disparity does not support,
    and those branches.

    `moved` holds the masks as carried over (`propagate_labels`), `refined` the same after the fine pass
    kept each branch's pixels whose disparity lies in its window (`roi.refine_labels`). A branch keeping
    under `min_support` of its carried-over pixels was carried to the wrong place (or is hidden now):
    its cut point would be measured on whatever lies there, so it is left out and a keyframe is due.
    """
    size = int(max(moved.max(initial=0), refined.max(initial=0))) + 1
    carried = np.bincount(moved.ravel(), minlength=size)
    supported = np.bincount(refined.ravel(), minlength=size)
    failed = tuple(b for b in branch_ids if 0 < b < size and carried[b] and supported[b] < min_support * carried[b])
    kept = refined if not failed else np.where(np.isin(refined, failed), 0, refined).astype(refined.dtype)
    return kept, failed
