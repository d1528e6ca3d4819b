"""A branch's or trunk's silhouette in the image: principal axis, ends and width along the axis.

The mask is exact where depth is not (near a junction, at thin tips), so ends and widths come from
the image; depth only places them in 3D. Pixels are (u, v) = (column, row).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from branchrange.core.masks import MaskCrop, as_crop

#: Slice length (px) along the axis over which the silhouette width is measured.
SLICE_PX = 2.0


@dataclass(frozen=True)
class ImageAxis:
    """Principal axis of a silhouette: centroid (u, v), unit `direction` and `normal` (px), every
    pixel's coordinate along (`s`) and across (`n`) the axis, and the extent `s_lo..s_hi` (px)."""

    centre: np.ndarray
    direction: np.ndarray
    normal: np.ndarray
    s: np.ndarray
    n: np.ndarray
    s_lo: float
    s_hi: float

    @property
    def length_px(self) -> float:
        """Length of the silhouette along its axis in pixels."""
        return self.s_hi - self.s_lo

    def point(self, s: float, n: float = 0.0) -> np.ndarray:
        """Pixel (u, v) at position `s` along and `n` across the axis."""
        return self.centre + s * self.direction + n * self.normal

    def coordinate(self, pixel: np.ndarray) -> float:
        """Position `s` (px) along the axis of a pixel (u, v)."""
        return float((np.asarray(pixel, dtype=np.float64) - self.centre) @ self.direction)

    def end_centre(self, at_low_end: bool, slice_px: float) -> np.ndarray:
        """Pixel on the centreline at one end (centre across the axis of the last `slice_px`)."""
        s_end = self.s_lo if at_low_end else self.s_hi
        in_slice = (self.s <= self.s_lo + slice_px) if at_low_end else (self.s >= self.s_hi - slice_px)
        n_mid = float(np.median(self.n[in_slice])) if np.any(in_slice) else 0.0
        return self.point(s_end, n_mid)


def touches_image_border(mask: np.ndarray | MaskCrop) -> bool:
    """Whether a boolean `H×W` mask reaches the first or last row or column (the image cuts it)."""
    return as_crop(mask).touches_image_border()


def _edge_direction(mask: MaskCrop, cut_by: MaskCrop | None) -> np.ndarray:
    """Unit (u, v) direction along which a mask's own edges run: the least eigenvector of the
    structure tensor of its gradient. The image border and the edges within 2 px of `cut_by`
    (e.g. the trunk) are cuts, not edges, and do not count.

    Why: where the image border and the trunk cut a short silhouette obliquely, the pixels'
    principal axis leans toward the cuts' diagonal, while the silhouette's sides still run along
    the branch. Computed on the crop (its ≥ 1 px background margin holds every non-zero gradient;
    the sums are of small integers, so exactly those of the whole image).
    """
    image = mask.mask.astype(np.float32)
    gu = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REPLICATE)
    gv = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REPLICATE)
    if cut_by is not None:
        h, w = image.shape
        around = cut_by.window(mask.top - 2, mask.left - 2, h + 4, w + 4)
        near_cut = cv2.dilate(around.astype(np.uint8), np.ones((5, 5), np.uint8))[2:-2, 2:-2].astype(bool)
        gu[near_cut], gv[near_cut] = 0.0, 0.0
    tensor = np.array([[np.sum(gu * gu), np.sum(gu * gv)], [np.sum(gu * gv), np.sum(gv * gv)]], dtype=np.float64)
    _, vectors = np.linalg.eigh(tensor)
    return vectors[:, 0]


def image_axis(mask: np.ndarray | MaskCrop, cut_by: np.ndarray | MaskCrop | None = None) -> ImageAxis:
    """`ImageAxis` of a non-empty boolean `H×W` mask or `MaskCrop` (with ≥ 1 px of background
    around it inside the image, as `BranchMasks.crop` gives); extent from the 0.2/99.8 % quantiles.

    Direction: the pixels' principal axis, or, for a silhouette the image border cuts, the
    direction of its own edges (`_edge_direction`; `cut_by`: where else the silhouette is cut).
    """
    crop = as_crop(mask)
    v, u = crop.pixels()
    pixels = np.stack([u, v], axis=1).astype(np.float64)
    centre = pixels.mean(axis=0)
    centred = pixels - centre
    _, vectors = np.linalg.eigh(centred.T @ centred)
    if touches_image_border(crop):
        direction = _edge_direction(crop, None if cut_by is None else as_crop(cut_by))
    else:
        direction = vectors[:, -1]
    normal = np.array([-direction[1], direction[0]])
    s, n = centred @ direction, centred @ normal
    s_lo, s_hi = np.quantile(s, [0.002, 0.998])
    return ImageAxis(centre, direction, normal, s, n, float(s_lo) - 0.5, float(s_hi) + 0.5)


@dataclass(frozen=True)
class WidthProfile:
    """Silhouette width (px) and centreline as straight lines in `s` (px along the image axis):
    `width(s) = intercept + slope·s`, centre offset across the axis `centre_intercept +
    centre_slope·s`.

    Fitted to per-slice widths with outlier slices trimmed, so a branch crossing the trunk, a
    twig hiding part of a branch or a stub at the junction does not bend it; a linear model
    follows the taper and the perspective change along the axis. The centreline (mid-points of
    the slices that kept their full width) is the projection of the cylinder's axis.
    """

    intercept: float
    slope: float
    centre_intercept: float = 0.0
    centre_slope: float = 0.0

    def at(self, s: float) -> float:
        """Width (px) at position `s`; never below one pixel."""
        return max(1.0, self.intercept + self.slope * s)

    def centre(self, axis: ImageAxis, s: float) -> np.ndarray:
        """Pixel (u, v) on the centreline at position `s`."""
        return axis.point(s, self.centre_intercept + self.centre_slope * s)


#: Pixels whose 16 sub-samples `_area_along` bins in one step.
_CROSSED_BLOCK = 2048


def _area_along(axis: ImageAxis, count: int) -> np.ndarray:
    """Mask area (px²) in each of `count` slices of `SLICE_PX` along the axis.

    Each pixel is spread over its footprint (4×4 sub-samples) rather than counted at its centre:
    at a slant, pixel centres fall into slices in a periodic pattern that would alias the widths.
    A sample's slice is monotone in its shift along the axis, so a pixel whose extreme sub-samples
    share a slice puts all 16 there; only the pixels a slice boundary crosses are sampled one by one.
    """
    offsets = (np.arange(4) + 0.5) / 4 - 0.5
    du, dv = np.meshgrid(offsets, offsets)
    shifts = du.ravel() * axis.direction[0] + dv.ravel() * axis.direction[1]

    def sub_sample_slices(s: np.ndarray, shift: float | np.ndarray) -> np.ndarray:
        return np.floor((s + shift - axis.s_lo) / SLICE_PX).astype(np.int64).ravel()

    def histogram(bins: np.ndarray) -> np.ndarray:
        return np.bincount(bins[(bins >= 0) & (bins < count)], minlength=count)

    first, last = sub_sample_slices(axis.s, shifts.min()), sub_sample_slices(axis.s, shifts.max())
    whole = first == last
    area = 16 * histogram(first[whole])
    crossed = axis.s[~whole]
    for start in range(0, crossed.size, _CROSSED_BLOCK):  # blocks of pixels × 16 samples that stay in cache
        area += histogram(sub_sample_slices(crossed[start : start + _CROSSED_BLOCK, None], shifts[None, :]))
    return area / 16.0


def _extent_along(axis: ImageAxis, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(extent across the axis, mid-point across the axis), px, of each of `count` slices.

    Extent = outermost pixel centres + 1 (0 for an empty slice).
    """
    bins = np.floor((axis.s - axis.s_lo) / SLICE_PX).astype(np.int64)
    inside = (bins >= 0) & (bins < count)
    high = np.full(count, -np.inf)
    low = np.full(count, np.inf)
    np.maximum.at(high, bins[inside], axis.n[inside])
    np.minimum.at(low, bins[inside], axis.n[inside])
    seen = np.isfinite(high)
    high, low = np.where(seen, high, 0.0), np.where(seen, low, 0.0)
    return np.where(seen, high - low + 1.0, 0.0), 0.5 * (high + low)


def width_profile(axis: ImageAxis, rounds: int = 3) -> WidthProfile:
    """Robust linear `WidthProfile` of a silhouette from slices of `SLICE_PX` along its axis.

    Occluders (leaves, twigs, crossing branches) only ever make a silhouette look narrower: a
    slice with a hole counts its outer extent, and slices well below the fitted line are dropped
    more readily than slices above it (an upper envelope, not a mean).
    """
    count = max(1, int(axis.length_px // SLICE_PX))
    widths = _area_along(axis, count) / SLICE_PX
    extents, mids = _extent_along(axis, count)
    widths = np.where(extents > widths + 1.5, extents, widths)
    centres = axis.s_lo + (np.arange(count) + 0.5) * SLICE_PX
    if count > 4:  # the end slices are partly outside the silhouette
        widths, mids, centres = widths[1:-1], mids[1:-1], centres[1:-1]
    if len(widths) < 4:
        return WidthProfile(float(np.max(widths)), 0.0)
    keep = widths > 0
    slope, intercept = 0.0, float(np.median(widths))
    for _ in range(rounds + 1):
        if keep.sum() < 3:
            break
        slope, intercept = np.polyfit(centres[keep], widths[keep], 1)
        residual = widths - (intercept + slope * centres)
        spread = 1.4826 * np.median(np.abs(residual[keep] - np.median(residual[keep])))
        keep = (residual >= -max(1.5 * spread, 0.5)) & (residual <= max(3.0 * spread, 1.5))
    if keep.sum() < 3:
        return WidthProfile(float(intercept), float(slope))
    centre_slope, centre_intercept = np.polyfit(centres[keep], mids[keep], 1)
    return WidthProfile(float(intercept), float(slope), float(centre_intercept), float(centre_slope))
