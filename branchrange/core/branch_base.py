"""Is a branch's base in view? A cut point is only as good as the base it is measured from.

A silhouette ends where the branch ends, where it meets the trunk, where the image border cuts it
or where something nearer hides it. Only the first two are a base: at the image border or behind
an occluder the true base lies further on, so a cut point placed `cut_offset_m` from the visible
end is a border artefact (flown approaches put it 29–36 cm from the truth, at confidence ≥ 0.94,
when the true cut point was 70–100 px below the bottom edge). Such a branch gives no cut point:
its visible part cannot say where the cut goes, and a confident wrong target is worse than none.

Pixels are (u, v) = (column, row) as in `branchrange.core.silhouette`; the checks read only the
branch's crop and a thin strip past its base end.
"""

from __future__ import annotations

import numpy as np

from branchrange.core.geometry import StereoGeometry, valid_disparity
from branchrange.core.masks import MaskCrop
from branchrange.core.silhouette import ImageAxis

#: Length (px, at least) of the end slice whose pixels decide whether the image border cuts the base.
END_SLICE_MIN_PX = 3.0
#: ... as a share of the silhouette's length.
END_SLICE_SHARE = 0.05
#: Width (px) of the strip just past the base end read for an occluder, and its gap from the end.
OCCLUDER_STRIP_PX, OCCLUDER_GAP_PX = 6.0, 1.5
#: Share of the strip's pixels that must have depth and lie nearer than the base for it to be hidden.
OCCLUDER_MIN_SHARE = 0.5
#: A base end within this many px of the trunk's mask meets the trunk: that end is real.
TRUNK_CONTACT_PX = 3.0


def _end_slice(silhouette: ImageAxis, at_low: bool) -> np.ndarray:
    """Boolean `(N,)` over the silhouette's pixels: those in the last slice at one end."""
    slice_px = max(END_SLICE_MIN_PX, END_SLICE_SHARE * silhouette.length_px)
    if at_low:
        return silhouette.s <= silhouette.s_lo + slice_px
    return silhouette.s >= silhouette.s_hi - slice_px


def base_cut_by_image_border(mask: MaskCrop, silhouette: ImageAxis, base_at_low: bool | None) -> bool:
    """Whether the image border cuts the silhouette at its base end.

    `silhouette` is `image_axis(mask)` (its `s`, `n` follow `mask.pixels()`'s order);
    `base_at_low` says which end is the base (None for a silhouette seen end-on, which has no ends:
    then any contact with the border counts, as the base cannot be told from the cut).
    """
    if base_at_low is None:
        return mask.touches_image_border()
    rows, cols = mask.pixels()
    in_slice = _end_slice(silhouette, base_at_low)
    height, width = mask.image_shape
    r, c = rows[in_slice], cols[in_slice]
    return bool(np.any((r == 0) | (r == height - 1) | (c == 0) | (c == width - 1)))


def base_hidden_by_occluder(
    mask: MaskCrop,
    silhouette: ImageAxis,
    base_at_low: bool,
    base_m: np.ndarray,
    disparity: np.ndarray,
    geometry: StereoGeometry,
    *,
    min_gap_m: float,
    trunk: MaskCrop | None,
    max_disparity: float | None = None,
) -> bool:
    """Whether something nearer than the base hides the silhouette where its base end stops.

    Reads the `H×W` disparity (px) in a strip `OCCLUDER_STRIP_PX` long just past the base end,
    as wide as the silhouette there, outside the branch's mask: the base is hidden when at least
    `OCCLUDER_MIN_SHARE` of those pixels have valid depth nearer than the base (`base_m` (3,), m)
    by more than `min_gap_m`. A base end touching the trunk's mask is real (the trunk's front,
    up to a trunk radius nearer, would otherwise pass for an occluder, hence also the gap), and
    without depth past the end nothing can be said: both count as not hidden.
    """
    end_u, end_v = silhouette.end_centre(base_at_low, max(END_SLICE_MIN_PX, END_SLICE_SHARE * silhouette.length_px))
    if trunk is not None and trunk.distances_at(np.array([round(end_v)]), np.array([round(end_u)]))[0] <= (
        TRUNK_CONTACT_PX
    ):
        return False
    in_slice = _end_slice(silhouette, base_at_low)
    half_width = 0.5 * (float(np.ptp(silhouette.n[in_slice])) + 1.0) if np.any(in_slice) else 1.0
    outward = -silhouette.direction if base_at_low else silhouette.direction
    along = np.arange(OCCLUDER_GAP_PX, OCCLUDER_GAP_PX + OCCLUDER_STRIP_PX)
    across = np.arange(-np.ceil(half_width), np.ceil(half_width) + 1.0)
    a, n = np.meshgrid(along, across, indexing="ij")
    u = np.rint(end_u + a * outward[0] + n * silhouette.normal[0]).astype(np.int64).ravel()
    v = np.rint(end_v + a * outward[1] + n * silhouette.normal[1]).astype(np.int64).ravel()
    height, width = disparity.shape
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v = u[inside], v[inside]
    if u.size == 0:
        return False
    own = mask.contains(v, u)
    u, v = u[~own], v[~own]
    if u.size == 0:
        return False
    d = disparity[v, u].astype(np.float64)
    valid = valid_disparity(d, max_disparity)
    base_z = float(base_m[2])
    nearer_than = geometry.fb / max(base_z - min_gap_m, 1e-3)  # disparity of a point min_gap_m nearer
    nearer = valid & (d > nearer_than) if base_z > min_gap_m else np.zeros_like(valid)
    return bool(nearer.mean() >= OCCLUDER_MIN_SHARE)
