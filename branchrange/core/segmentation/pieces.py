"""Splitting thin regions into straight pieces: the two arms of a fork, two crossing stems, two branches
that touch in the image become separate instances (sequential RANSAC of image lines of the region's own
width, contiguous runs along each). Used by the structure and learned segmenters.

Why lines: a branch between its base and its first bend is close to straight in the image, and the
cut-point geometry fits one straight axis per instance — a region holding two branches gives an axis
between them and a cut point on neither.

Given the disparity, a line is also a line in depth: for a straight branch the disparity is affine along
its image line (a 3D line maps to a line in (u, v, 1/Z)), so a line's inliers must lie near the disparity
drawn between its two sample pixels. A thin stem that crosses a thicker branch in the image, or leaves the
trunk beside it at a shallow angle, lies within the thicker one's band but at another depth; without the
test the thicker one's line takes the stem's base and the stem's cut point is lost.
"""

from __future__ import annotations

from collections.abc import Iterator

import cv2
import numpy as np

#: neighbourhood (px) over which the inscribed radius gives a pixel's local branch width
LOCAL_WIDTH_PX = 3
#: a line's inlier lies within this many px of the line's disparity, or its relative share, whichever is
#: larger (SGBM's noise on textured surfaces is ~0.25 px)
PIECE_MIN_DISPARITY_PX = 0.3


def straight_pieces(
    u: np.ndarray,
    v: np.ndarray,
    band_px: np.ndarray,
    min_px: int,
    rng: np.random.Generator,
    max_pieces: int = 6,
    min_gap_px: float = 4.0,
    disparity: np.ndarray | None = None,
    disparity_ratio: float = 0.0,
) -> list[np.ndarray]:
    """Index arrays of straight, contiguous runs of the pixels (u, v) `(N,)`, longest consensus first.

    `band_px` `(N,)` is the half-width of a line's inlier band when drawn through that pixel; a line through
    two pixels takes the wider of their bands, so a thin stem beside a thick limb gets its own narrow line
    rather than being swallowed by the limb's wide one. With `disparity` `(N,)` (px, NaN where unknown) and
    `disparity_ratio` > 0, an inlier must also lie within max(`disparity_ratio` × the line's disparity,
    `PIECE_MIN_DISPARITY_PX`) of the disparity affine along the line between its two sample pixels (see the
    module docstring); pixels or samples without a disparity pass that test."""
    points = np.stack([u, v], axis=1).astype(np.float64)
    remaining = np.arange(len(points))
    pieces: list[np.ndarray] = []
    while len(remaining) >= min_px and len(pieces) < max_pieces:
        pts = points[remaining]
        pairs = rng.integers(0, len(pts), size=(80, 2))
        d = pts[pairs[:, 1]] - pts[pairs[:, 0]]
        length = np.sqrt(np.add.reduce(d * d, axis=1))  # np.linalg.norm's own sum, without its overhead
        ok = length > 2.0
        if not ok.any():
            break
        direction = d[ok] / length[ok, None]
        normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)
        origin = pts[pairs[ok, 0]]
        remaining_band = band_px[remaining]
        bands = np.maximum(remaining_band[pairs[ok, 0]], remaining_band[pairs[ok, 1]])  # (K,)
        offset = np.einsum("kc,kc->k", origin, normal)
        known = None if disparity is None or disparity_ratio <= 0 else disparity[remaining]
        inside = np.empty((len(pts), len(bands)), dtype=bool)  # (N, K): in each line's band (and on its disparity)
        for rows in _blocks(len(pts)):  # a block's (·, K) temporaries stay in the core's cache
            block = inside[rows]
            np.less(np.abs(pts[rows] @ normal.T - offset), bands, out=block)
            if known is not None:
                block &= _on_disparity_line(
                    pts[rows], known[rows], known, pairs[ok], origin, direction, length[ok], disparity_ratio
                )
        best = int(np.argmax(inside.sum(axis=0)))
        inliers = np.flatnonzero(inside[:, best])
        gap = max(min_gap_px, 2.0 * float(bands[best]))
        along = (pts[inliers] - origin[best]) @ direction[best]
        order = np.argsort(along)
        bounds = np.concatenate(([0], np.flatnonzero(np.diff(along[order]) > gap) + 1, [len(order)]))
        longest = int(np.argmax(np.diff(bounds)))  # the first longest run
        run = order[bounds[longest] : bounds[longest + 1]]
        if len(run) < min_px:
            break
        pieces.append(remaining[inliers[run]])
        unchosen = np.ones(len(remaining), dtype=bool)
        unchosen[inliers[run]] = False
        remaining = remaining[unchosen]
    return pieces


#: rows of the (points × lines) tests computed at once in `straight_pieces`: 80 float64 lines × 512 points
#: are 320 kB a temporary, within a core's L2 cache, where a large region's whole (N, K) arrays (N ~ 20,000 at
#: HD720: 13 MB each) went to memory and back for every step
BLOCK_POINTS = 512


def _blocks(count: int) -> Iterator[slice]:
    """Consecutive slices of `BLOCK_POINTS` rows covering `range(count)`."""
    for start in range(0, count, BLOCK_POINTS):
        yield slice(start, min(start + BLOCK_POINTS, count))


def _on_disparity_line(
    points: np.ndarray,
    disparity: np.ndarray,
    sampled: np.ndarray,
    pairs: np.ndarray,
    origin: np.ndarray,
    direction: np.ndarray,
    length: np.ndarray,
    ratio: float,
) -> np.ndarray:
    """Boolean `(N, K)`: whether each of the `(N, 2)` `points` (disparity `(N,)` px, NaN unknown) lies near
    the disparity of each of K candidate lines — affine along the line from its sample pair's (`pairs`
    `(K, 2)` indices into `sampled`, the disparities the pairs were drawn from) disparities, the line running
    from `origin` `(K, 2)` along the unit `direction` `(K, 2)` to the second sample `length` `(K,)` px away —
    within max(`ratio` × the line's disparity, `PIECE_MIN_DISPARITY_PX`). Unknown disparities, a point's or a
    sample's, pass."""
    first, second = sampled[pairs[:, 0]], sampled[pairs[:, 1]]
    along = (points @ direction.T - np.einsum("kc,kc->k", origin, direction)) / length  # (N, K), 0..1 between
    expected = first + along * (second - first)
    with np.errstate(invalid="ignore"):  # NaN compares False: an unknown disparity is checked below
        near = np.abs(disparity[:, None] - expected) <= np.maximum(PIECE_MIN_DISPARITY_PX, ratio * np.abs(expected))
    return np.asarray(near | np.isnan(disparity)[:, None] | np.isnan(expected))


def straight_pieces_of(
    mask: np.ndarray,
    min_px: int,
    rng: np.random.Generator,
    bridge_px: int = 0,
    disparity: np.ndarray | None = None,
    disparity_ratio: float = 0.0,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(u, v) pixel arrays of the straight pieces of every 8-connected region of the boolean `H×W` `mask`
    with at least `min_px` pixels; a line's band is 1.2× the largest inscribed radius (≥ 1.5 px) within
    `LOCAL_WIDTH_PX` of the pixels it is drawn through — the local width of the branch there. With the
    `H×W` `disparity` (px; ≤ 0 or not finite = unknown) and `disparity_ratio` > 0, a line's pixels also follow its
    disparity (`straight_pieces`).

    The distances are taken in the mask's bounding box grown by the bridge and a pixel of background
    (`padded_box`): a mask's distances to its edge are the same there as in the whole frame, and an HD720
    frame's full-resolution branches fill a fraction of it. The regions are labelled over the whole frame:
    their order sets the random lines each is tried with, and OpenCV numbers a box's regions in another order
    than the frame's (its labelling runs in stripes)."""
    rows, cols = padded_box(mask, bridge_px + 1)
    if rows.stop == rows.start:
        return
    window = mask[rows, cols]
    inside = cv2.distanceTransform(window.astype(np.uint8), cv2.DIST_L2, 3)
    local_radius = cv2.dilate(inside, np.ones((2 * LOCAL_WIDTH_PX + 1,) * 2, np.uint8))
    # connectedComponentsWithStats costs ~10× more: its statistics cover the background too
    count, components = bridged_regions(mask, bridge_px)
    pixels = np.flatnonzero(window)
    region = components[rows, cols].ravel()[pixels]
    pixels = pixels[np.argsort(region, kind="stable")]  # by region, each region's in raster order
    ends = np.cumsum(np.bincount(region, minlength=count))
    known_disparity = None
    if disparity is not None and disparity_ratio > 0:
        own = disparity[rows, cols]
        known_disparity = np.where(np.isfinite(own) & (own > 0), own, np.nan)
    gap = max(4.0, 2.0 * bridge_px + 1.0)
    for i in range(1, count):
        if ends[i] - ends[i - 1] < min_px:
            continue
        v, u = np.divmod(pixels[ends[i - 1] : ends[i]], window.shape[1])
        band = np.maximum(1.5, 1.2 * local_radius[v, u])
        known = None if known_disparity is None else known_disparity[v, u]
        for piece in straight_pieces(
            u, v, band, min_px, rng, min_gap_px=gap, disparity=known, disparity_ratio=disparity_ratio
        ):
            yield u[piece] + cols.start, v[piece] + rows.start


def bridged_region_of(mask: np.ndarray, bridge_px: int, pixels: np.ndarray) -> tuple[np.ndarray, int]:
    """(`int32 (N,)` bridged region of each of the flat indices `pixels` of the boolean `H×W` `mask`'s pixels,
    the count of labels): `bridged_regions` found in the mask's box grown by the bridge and a pixel
    (`padded_box`), where the regions are those of the whole frame (numbered in another order), at a
    fraction of its cost."""
    if pixels.size == 0:
        return np.zeros(0, dtype=np.int32), 1
    rows, cols = padded_box(mask, bridge_px + 1)
    count, labels = bridged_regions(mask[rows, cols], bridge_px)
    row, col = np.divmod(pixels, mask.shape[1])
    return labels[row - rows.start, col - cols.start], count


def padded_box(mask: np.ndarray, margin_px: int) -> tuple[slice, slice]:
    """(rows, columns) of the boolean `H×W` `mask`'s bounding box grown by `margin_px` on every side, clipped to
    the frame; empty slices when the mask is empty."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return slice(0, 0), slice(0, 0)
    height, width = mask.shape
    return (
        slice(max(int(rows[0]) - margin_px, 0), min(int(rows[-1]) + margin_px + 1, height)),
        slice(max(int(cols[0]) - margin_px, 0), min(int(cols[-1]) + margin_px + 1, width)),
    )


def bridged_regions(mask: np.ndarray, bridge_px: int) -> tuple[int, np.ndarray]:
    """(count, `int32 H×W` labels) of the boolean `H×W` `mask`'s regions, 8-connected across gaps of up to
    2·`bridge_px` px (0: 8-connected as they are): a stem seen through leaves shows as fragments along its
    line, and only together do they hold enough pixels for a piece. Labels outside `mask` are meaningless."""
    grouping = mask.astype(np.uint8)
    if bridge_px > 0:
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * bridge_px + 1,) * 2)
        grouping = np.asarray(cv2.dilate(grouping, disc), dtype=np.uint8)
    count, labels = cv2.connectedComponents(grouping, connectivity=8)
    return int(count), labels
