"""Which trunk pixels are the trunk of the tree being pruned, and how far each pixel is from it.

A segmenter's trunk class marks every trunk-like thing in view: the tree in front, its silhouette cut
in pieces by branches crossing before it, other trees, posts, a frame. The tree being pruned is the
trunk region that branches grow from — the one with the most branch pixels beside it at its own
depth (the largest region when no branch touches any) — joined by the regions at that depth that
are large enough to be its other parts.
"""

from __future__ import annotations

import cv2
import numpy as np

from branchrange.core.geometry import StereoGeometry

#: a trunk region joins the tree's when it has this share of the largest region's pixels and lies at
#: the tree's depth ± this share; a branch pixel supports a region within this share of its depth too
TRUNK_PART_MIN_AREA, TRUNK_DEPTH_TOLERANCE = 0.05, 0.15


def tree_trunk(
    trunk_px: np.ndarray, branch_px: np.ndarray, depth: np.ndarray, geometry: StereoGeometry, max_gap_m: float
) -> np.ndarray:
    """Boolean `H×W`: the tree's trunk (see the module docstring) among the boolean `H×W` `trunk_px`,
    given the branch pixels `branch_px`, the depth (m, `H×W`, inf where unknown) and how far from the
    trunk (m, in the image at the branch's depth) a branch may start, `max_gap_m`."""
    count, components, stats, _ = cv2.connectedComponentsWithStats(trunk_px.astype(np.uint8), connectivity=8)
    if count < 2:
        return np.zeros(trunk_px.shape, dtype=bool)
    areas = stats[:, cv2.CC_STAT_AREA].copy()
    areas[0] = 0
    candidates = np.flatnonzero(areas >= TRUNK_PART_MIN_AREA * areas.max())
    rows, cols = np.nonzero(components)  # the trunk pixels only: a few % of the frame
    depths = _median_depths(components[rows, cols], depth[rows, cols], candidates, count)
    support = _branch_support(components, (rows, cols), depths, branch_px, depth, geometry, max_gap_m)
    anchor = int(np.argmax(support)) if support.max() > 0 else int(np.argmax(areas))
    keep = np.zeros(count, dtype=bool)
    keep[anchor] = True
    if np.isfinite(depths[anchor]):
        keep[candidates] = np.abs(depths[candidates] - depths[anchor]) <= TRUNK_DEPTH_TOLERANCE * depths[anchor]
    return np.asarray(keep[components], dtype=bool)


def _median_depths(region: np.ndarray, depth: np.ndarray, candidates: np.ndarray, count: int) -> np.ndarray:
    """`(count,)` median finite depth (m) of each candidate region over its pixels (`region`, `depth` `(N,)`);
    inf for the other regions and for candidates without a valid depth."""
    medians = np.full(count, np.inf)
    finite = np.isfinite(depth)
    region, depth = region[finite], depth[finite]
    order = np.argsort(region, kind="stable")
    region, depth = region[order], depth[order]
    starts = np.searchsorted(region, candidates, side="left")
    ends = np.searchsorted(region, candidates, side="right")
    for k, start, end in zip(candidates, starts, ends):
        if end > start:
            medians[k] = float(np.median(depth[start:end]))
    return medians


def _branch_support(
    components: np.ndarray,
    trunk_pixels: tuple[np.ndarray, np.ndarray],
    depths: np.ndarray,
    branch_px: np.ndarray,
    depth: np.ndarray,
    geometry: StereoGeometry,
    max_gap_m: float,
) -> np.ndarray:
    """`(regions,)`: per trunk region (`components` `int32 H×W`, 0 = none, with its pixels `trunk_pixels`
    (rows, cols); `depths` its median depth, inf when not a candidate), the branch pixels whose nearest
    trunk pixel is that region's, within `max_gap_m` in the image and within `TRUNK_DEPTH_TOLERANCE` of
    the region's depth."""
    gap_px, nearest = cv2.distanceTransformWithLabels(
        (components == 0).astype(np.uint8), cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL
    )
    tv, tu = trunk_pixels
    region_of = np.zeros(int(nearest.max()) + 1, dtype=np.int64)
    region_of[nearest[tv, tu]] = components[tv, tu]
    bv, bu = np.nonzero(branch_px & np.isfinite(depth))
    region = region_of[nearest[bv, bu]]
    z = depth[bv, bu]
    close = gap_px[bv, bu] * z / geometry.focal_px <= max_gap_m
    with np.errstate(invalid="ignore"):  # regions that are not candidates have no depth: never the same
        same_depth = np.abs(depths[region] - z) <= TRUNK_DEPTH_TOLERANCE * depths[region]
    return np.bincount(region[close & same_depth & np.isfinite(depths[region])], minlength=len(depths))


def trunk_gap_m(trunk: np.ndarray, depth: np.ndarray, geometry: StereoGeometry) -> np.ndarray:
    """`H×W` metres from each pixel to the boolean `H×W` `trunk` in the image, at the pixel's own depth
    (`H×W` m; inf where unknown).

    What a pruner cuts grows from the trunk: a piece far from it is a twig, the far part of a branch
    whose base is hidden, a leaf or background — its cut point would be wrong, so it is not reported.
    """
    gap_px = cv2.distanceTransform((~trunk).astype(np.uint8), cv2.DIST_L2, 3)
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(depth), gap_px * depth / geometry.focal_px, np.inf)
