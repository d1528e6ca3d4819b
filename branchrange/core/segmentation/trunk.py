"""Which trunk pixels are the trunk of the tree being pruned, which lie in front of it, and how far each
pixel is from it.

A segmenter's trunk class marks every trunk-like thing in view: the tree in front, its silhouette cut
in pieces by branches crossing before it, other trees, posts, a frame. The tree being pruned is the
trunk region that branches grow from — the one with the most branch pixels beside it at its own
depth (the largest region when no branch touches any) — joined by the regions large enough to be its
other parts that lie where its surface runs (its inverse depth, affine in the image, carried to them: a
trunk seen from below recedes along its length) and continue its line in the image: a branch crossing
in front cuts the trunk's silhouette into pieces along its axis, while a post, a stake or another trunk
at the same depth stands beside it (`_continues_trunk`).

A thin stem seen against the bark is easily called trunk by the image alone (dark on dark, 2–3 px
wide); the disparity tells it apart, since it is nearer than the bark on both of its sides
(`in_front_of_trunk`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from branchrange.core.geometry import StereoGeometry

#: a trunk region joins the tree's when it has this share of the largest region's pixels and lies at
#: the tree's depth ± this share; a branch pixel supports a region within this share of its depth too
TRUNK_PART_MIN_AREA, TRUNK_DEPTH_TOLERANCE = 0.05, 0.15
#: `in_front_of_trunk`: the bark beside a pixel is the trunk's mean disparity 3..10 px away on each side
#: (a stem up to ~6 px wide fits between them; a trunk's own bulge changes under 1 % over 10 px), taken
#: where ≥ 3 trunk pixels with a disparity lie; a pixel must be nearer by ≥ this many px as well as by
#: the relative margin (SGBM's noise on bark is ~0.25 px)
FRONT_SIDE_PX, FRONT_MIN_SIDE_PIXELS, FRONT_MIN_DISPARITY_PX = (3, 10), 3, 0.3
#: a region in front of the trunk is a stem only when this elongated (area over its largest inscribed
#: disc's): leaves before the bark and SGBM's blotches on it are rounder (calibration scenes, as length
#: over width: stems median 4.9, leaves 2.4, SGBM blotches 2.2)
FRONT_MIN_ELONGATION = 2.5
#: a trunk region continues the tree's trunk when the median distance of its pixels from the trunk's
#: image axis is at most this many of the trunk's half-widths plus a margin (px); judged only when the
#: trunk region is elongated (length ≥ this many widths, from its pixels' second moments). Without it a
#: post at the trunk's depth joined the trunk, and the trunk's cylinder was fitted across both: with orchard
#: hardware (calibration scenes 2861–2920), recall within 5 cm 56.7 → 58.3 %, false cut points 7.22 → 6.43
#: a frame, 0.45 → 0.33 at the target threshold; held out 55.3 → 60.3 %; without hardware within a branch
TRUNK_PART_AXIS_WIDTHS, TRUNK_PART_AXIS_MARGIN_PX, TRUNK_AXIS_MIN_ELONGATION = 1.5, 3.0, 3.0


def tree_trunk(
    trunk_px: np.ndarray, branch_px: np.ndarray, depth: np.ndarray, geometry: StereoGeometry, max_gap_m: float
) -> np.ndarray:
    """Boolean `H×W`: the tree's trunk (see the module docstring) among the boolean `H×W` `trunk_px`,
    given the branch pixels `branch_px`, the depth (m, `H×W`, inf where unknown) and how far from the
    trunk (m, in the image at the branch's depth) a branch may start, `max_gap_m`."""
    # connectedComponentsWithStats costs ~10× more: its statistics cover the background too
    count, components = cv2.connectedComponents(trunk_px.astype(np.uint8), connectivity=8)
    if count < 2:
        return np.zeros(trunk_px.shape, dtype=bool)
    pixels = np.flatnonzero(components)  # the trunk pixels only (a few % of the frame), as flat indices
    region = components.ravel()[pixels]
    areas = np.bincount(region, minlength=count)
    candidates = np.flatnonzero(areas >= TRUNK_PART_MIN_AREA * areas.max())
    depths = _median_per_region(region, depth.ravel()[pixels], candidates, count)
    support = _branch_support(components, pixels, region, depths, branch_px, depth, geometry, max_gap_m)
    anchor = int(np.argmax(support)) if support.max() > 0 else int(np.argmax(areas))
    keep = np.zeros(count, dtype=bool)
    others = candidates[candidates != anchor]
    if np.isfinite(depths[anchor]) and others.size:
        rows, cols = np.divmod(pixels, components.shape[1])
        keep[others] = _continues_trunk((rows, cols), region, depth.ravel()[pixels], depths, anchor, others, count)
    keep[anchor] = True
    trunk = np.zeros(trunk_px.shape, dtype=bool)
    trunk.ravel()[pixels] = keep[region]
    return trunk


def _median_per_region(region: np.ndarray, values: np.ndarray, candidates: np.ndarray, count: int) -> np.ndarray:
    """`(count,)` median finite value of each candidate region over its pixels (`region`, `values` `(N,)`);
    inf for the other regions and for candidates without a finite value."""
    medians = np.full(count, np.inf)
    finite = np.isfinite(values)
    region, values = region[finite], values[finite]
    order = np.argsort(region, kind="stable")
    region, values = region[order], values[order]
    starts = np.searchsorted(region, candidates, side="left")
    ends = np.searchsorted(region, candidates, side="right")
    for k, start, end in zip(candidates, starts, ends):
        if end > start:
            medians[k] = float(np.median(values[start:end]))
    return medians


@dataclass(frozen=True)
class _Axis:
    """A trunk region's image axis: `centre` (x, y) px, unit `along` and `across` directions, and the
    standard deviation of its pixels across it (px)."""

    centre: np.ndarray
    along: np.ndarray
    across: np.ndarray
    spread_px: float


def _anchor_axis(pixels: tuple[np.ndarray, np.ndarray], own: np.ndarray) -> _Axis | None:
    """The principal axis of the trunk pixels `pixels` (rows, cols) selected by the boolean `own`; None when
    the region is too short for one (length < `TRUNK_AXIS_MIN_ELONGATION` widths) or has < 3 pixels."""
    rows, cols = pixels
    points = np.stack([cols[own], rows[own]], axis=1).astype(np.float64)
    if len(points) < 3:
        return None
    centre = points.mean(axis=0)
    variances, directions = np.linalg.eigh(np.cov((points - centre).T))  # ascending: across, then along
    if variances[1] < TRUNK_AXIS_MIN_ELONGATION**2 * variances[0]:
        return None
    return _Axis(centre, directions[:, 1], directions[:, 0], math.sqrt(max(variances[0], 0.0)))


def _continues_trunk(
    pixels: tuple[np.ndarray, np.ndarray],
    region: np.ndarray,
    depth: np.ndarray,
    region_depths: np.ndarray,
    anchor: int,
    others: np.ndarray,
    count: int,
) -> np.ndarray:
    """`(len(others),)` bool: which of the regions `others` continue the `anchor` region's trunk — in depth:
    their median depth (`region_depths` `(count,)`) within `TRUNK_DEPTH_TOLERANCE` of the anchor's surface
    carried to where they lie (`_inverse_depth_plane`); and, when the anchor is long enough for an axis
    (`_anchor_axis`), in the image: the median distance of their pixels from its axis within
    `TRUNK_PART_AXIS_WIDTHS` of its half-widths (2 standard deviations across) plus
    `TRUNK_PART_AXIS_MARGIN_PX`. `pixels` (rows, cols), `region` and `depth` (m, inf unknown) are per trunk
    pixel `(N,)`. Why the surface and not the anchor's own depth: a trunk seen from below or above recedes
    along its length (held out, one trunk's parts lay at 0.99 and 1.63 m), and the branches on its far parts
    were dropped as far from the trunk."""
    rows, cols = pixels
    own = region == anchor
    along_u, along_v, constant = _inverse_depth_plane(cols[own], rows[own], depth[own])
    u = _median_per_region(region, cols.astype(np.float64), others, count)[others]
    v = _median_per_region(region, rows.astype(np.float64), others, count)[others]
    inverse = along_u * u + along_v * v + constant
    with np.errstate(divide="ignore"):
        expected = np.where(inverse > 0, 1.0 / inverse, np.inf)
    depths = region_depths[others]
    # where the fitted surface runs off to infinity (a steep fit carried far) or a region has no depth there is
    # nothing to compare: such a region does not join (inf ≤ tolerance · inf would have joined it)
    judged = np.isfinite(expected) & np.isfinite(depths)
    continues = np.zeros(len(others), dtype=bool)
    continues[judged] = np.abs(depths[judged] - expected[judged]) <= TRUNK_DEPTH_TOLERANCE * expected[judged]
    axis = _anchor_axis(pixels, own)
    if axis is not None:
        points = np.stack([cols, rows], axis=1).astype(np.float64) - axis.centre
        across = _median_per_region(region, np.abs(points @ axis.across), others, count)[others]
        continues &= across <= TRUNK_PART_AXIS_WIDTHS * 2.0 * axis.spread_px + TRUNK_PART_AXIS_MARGIN_PX
    return np.asarray(continues, dtype=bool)


#: `_inverse_depth_plane` refits without the pixels farther from its first fit than this many MADs
_PLANE_TRIM_MADS = 2.5


def _inverse_depth_plane(cols: np.ndarray, rows: np.ndarray, depth: np.ndarray) -> tuple[float, float, float]:
    """(a, b, c) of 1/depth ≈ a·col + b·row + c over a trunk region's pixels `(N,)` (depth m, inf unknown): the
    inverse depth of a plane is affine in its image position, and a trunk's bark is a plane to first order
    along its length. Least squares, then again without the pixels beyond `_PLANE_TRIM_MADS` MADs (SGBM's
    fattened edges, holes); a flat (0, 0, median) with fewer than 10 depths."""
    finite = np.isfinite(depth) & (depth > 0)
    if finite.sum() < 10:
        inverse = 1.0 / depth[finite]
        return 0.0, 0.0, float(np.median(inverse)) if inverse.size else 0.0
    design = np.stack([cols[finite], rows[finite], np.ones(int(finite.sum()))], axis=1).astype(np.float64)
    inverse = 1.0 / depth[finite].astype(np.float64)
    coefficients = np.linalg.lstsq(design, inverse, rcond=None)[0]
    residual = np.abs(design @ coefficients - inverse)
    inliers = residual <= _PLANE_TRIM_MADS * max(float(np.median(residual)) * 1.4826, 1e-9)
    if inliers.sum() >= 10:
        coefficients = np.linalg.lstsq(design[inliers], inverse[inliers], rcond=None)[0]
    return float(coefficients[0]), float(coefficients[1]), float(coefficients[2])


def _branch_support(
    components: np.ndarray,
    trunk_pixels: np.ndarray,
    trunk_region: np.ndarray,
    depths: np.ndarray,
    branch_px: np.ndarray,
    depth: np.ndarray,
    geometry: StereoGeometry,
    max_gap_m: float,
) -> np.ndarray:
    """`(regions,)`: per trunk region (`components` `int32 H×W`, 0 = none; `trunk_pixels` `(N,)` the flat
    indices of its nonzero pixels, `trunk_region` `(N,)` their regions; `depths` each region's median depth,
    inf when not a candidate), the branch pixels whose nearest trunk pixel is that region's, within
    `max_gap_m` in the image and within `TRUNK_DEPTH_TOLERANCE` of the region's depth.

    The distances are taken in the bounding box of the trunk and the branch pixels (`pixel_box`): a 3×3
    chamfer distance between two pixels runs inside their own bounding box, so it is the frame's there."""
    branch = np.flatnonzero(branch_px & np.isfinite(depth))
    box = pixel_box(components.shape, trunk_pixels, branch)
    gap_px, nearest = cv2.distanceTransformWithLabels(
        (components[box.rows, box.cols] == 0).astype(np.uint8), cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL
    )
    region_of = np.zeros(int(nearest.max()) + 1, dtype=np.int64)
    region_of[nearest.ravel()[box.local(trunk_pixels)]] = trunk_region
    in_box = box.local(branch)
    region = region_of[nearest.ravel()[in_box]]
    z = depth.ravel()[branch]
    close = gap_px.ravel()[in_box] * z / geometry.focal_px <= max_gap_m
    with np.errstate(invalid="ignore"):  # regions that are not candidates have no depth: never the same
        same_depth = np.abs(depths[region] - z) <= TRUNK_DEPTH_TOLERANCE * depths[region]
    return np.bincount(region[close & same_depth & np.isfinite(depths[region])], minlength=len(depths))


@dataclass(frozen=True)
class PixelBox:
    """A box of an `H×W` frame (`rows`, `cols` slices) and the frame's `width` (px)."""

    rows: slice
    cols: slice
    width: int

    def local(self, pixels: np.ndarray) -> np.ndarray:
        """The frame's flat indices `pixels` `(N,)` (inside the box) as flat indices of the box."""
        rows, cols = np.divmod(pixels, self.width)
        return np.asarray((rows - self.rows.start) * (self.cols.stop - self.cols.start) + (cols - self.cols.start))


def pixel_box(shape: tuple[int, ...], *pixels: np.ndarray) -> PixelBox:
    """The bounding box of the flat indices `pixels` (arrays `(N_i,)`, not all empty) of an `H×W` frame."""
    every = np.concatenate(pixels)
    width = shape[1]
    rows, cols = np.divmod(every, width)
    return PixelBox(slice(int(rows.min()), int(rows.max()) + 1), slice(int(cols.min()), int(cols.max()) + 1), width)


def trunk_gap_m(trunk: np.ndarray, depth: np.ndarray, geometry: StereoGeometry, pixels: np.ndarray) -> np.ndarray:
    """`(N,)` metres from the pixels at the flat indices `pixels` `(N,)` to the boolean `H×W` `trunk` in the
    image, at the pixel's own depth (`H×W` m; inf where unknown).

    What a pruner cuts grows from the trunk: a piece far from it is a twig, the far part of a branch
    whose base is hidden, a leaf or background — its cut point would be wrong, so it is not reported.
    """
    if not trunk.any() or pixels.size == 0:  # no trunk: every gap is OpenCV's "far"
        gap_px = cv2.distanceTransform((~trunk).astype(np.uint8), cv2.DIST_L2, 3).ravel()[pixels]
    else:  # in the bounding box of the trunk and the pixels, as `_branch_support`
        box = pixel_box(trunk.shape, np.flatnonzero(trunk), pixels)
        window = trunk[box.rows, box.cols]
        gap_px = cv2.distanceTransform((~window).astype(np.uint8), cv2.DIST_L2, 3).ravel()[box.local(pixels)]
    z = depth.ravel()[pixels]
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(z), gap_px * z / geometry.focal_px, np.inf)


def in_front_of_trunk(trunk: np.ndarray, disparity: np.ndarray, ratio: float, min_area_px: int) -> np.ndarray:
    """Boolean `H×W`: the pixels of the boolean `H×W` `trunk` that lie in front of it — stems before the bark.

    A pixel qualifies when its disparity (px, `H×W`, ≤ 0 or non-finite = unknown) exceeds the bark's on
    both sides — left and right, or above and below (`FRONT_SIDE_PX`) — by `ratio` of it and by
    `FRONT_MIN_DISPARITY_PX`; such pixels count in 8-connected regions of ≥ `min_area_px` pixels that
    are elongated (`FRONT_MIN_ELONGATION`). At the trunk's silhouette edge one side is missing, so
    nothing there qualifies.
    """
    known = trunk & np.isfinite(disparity) & (disparity > 0)
    front = np.zeros(trunk.shape, dtype=bool)
    if not known.any():
        return front
    near, far = FRONT_SIDE_PX
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    top, left = max(0, int(rows[0]) - far), max(0, int(cols[0]) - far)
    window = (slice(top, int(rows[-1]) + far + 1), slice(left, int(cols[-1]) + far + 1))
    weight = known[window].astype(np.float32)
    values = np.where(known[window], disparity[window], 0.0).astype(np.float32)
    side = np.zeros(2 * far + 1, dtype=np.float32)
    side[far + near :] = 1.0  # one side's offsets near..far; mirrored for the other side
    nearer = np.zeros(weight.shape, dtype=bool)
    for along_rows in (True, False):
        bark = []
        for one_side in (side, side[::-1].copy()):
            kernel = one_side[None, :] if along_rows else one_side[:, None]
            total = cv2.filter2D(values, -1, kernel, borderType=cv2.BORDER_CONSTANT)
            count = cv2.filter2D(weight, -1, kernel, borderType=cv2.BORDER_CONSTANT)
            bark.append(np.where(count >= FRONT_MIN_SIDE_PIXELS, total / np.maximum(count, 1.0), np.inf))
        nearer_side = np.maximum(bark[0], bark[1])  # the larger disparity: the pixel must be before both sides
        nearer |= values > nearer_side + np.maximum(ratio * nearer_side, FRONT_MIN_DISPARITY_PX)
    # the window's margin keeps `known`'s regions and their inscribed discs whole: judged there, not frame-wide
    front[window] = _elongated_regions(nearer & known[window], min_area_px)
    return front


def _elongated_regions(mask: np.ndarray, min_area_px: int) -> np.ndarray:
    """The 8-connected regions of the boolean `H×W` `mask` with ≥ `min_area_px` pixels that are elongated:
    their area is ≥ `FRONT_MIN_ELONGATION` times that of their largest inscribed disc — the length-to-width
    ratio of an ellipse or a straight stem, and it holds for a bent or crossed stem too."""
    count, regions = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    if count < 2:
        return mask
    inscribed = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    pixels = np.flatnonzero(regions)
    region = np.asarray(regions.ravel()[pixels], dtype=np.intp)
    area = np.bincount(region, minlength=count)
    radius = np.zeros(count, dtype=np.float32)
    np.maximum.at(radius, region, inscribed.ravel()[pixels])
    keep = (area >= min_area_px) & (area >= FRONT_MIN_ELONGATION * np.pi * radius**2)
    keep[0] = False
    return np.asarray(keep[regions], dtype=bool)
