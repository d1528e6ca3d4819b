"""The roi mode's region budget: each branch matched at the coarsest scale its cut point can afford.

Why: a branch's full-resolution region grows with proximity — its box as 1/Z², its disparity window as
1/Z — so the fine pass, and every per-pixel stage after it, cost most exactly when the vehicle is near the
tree and the autopilot needs the result soonest (issue 37: 47 → 140 kpx of regions a frame from 3 m to
0.8 m at HD720). But near the tree the disparity is large, so the precision need is smaller: depth
precision relative to range is σ_d / d, and at twice the disparity half the pixels give the same.

The rule, per region (`working_scale`): the largest power of two s ≤ `roi.budget_max_scale` with, at the
working scale (the pair shrunk s times),
- the branch's disparity d / s ≥ `roi.budget_min_disparity_px` (D): its relative depth precision at
  least that of a full-resolution branch at disparity D (16 px at HD720: ~2.5 m with the ZED Mini); and
- its width w / s ≥ `roi.budget_min_diameter_px` (K): a stem the block matcher can still see.
`d` is the branch's median coarse disparity (× the coarse scale; a branch without coarse evidence stays at
full resolution), `w` its mask's pixel count over its box diagonal (the mean width of a straight stem).
Then the frame's budget (`fit_budget`): the regions' pixels at their working scale Σ (w·h)/s² ≤
`roi.budget_max_pixels` and their matching cost Σ (w·h)/s² · D_s ≤ `roi.budget_max_cost_mpd` million
pixel-disparities (D_s the disparities searched at that scale, in SGBM's steps of 16). Over it, the region
with the most disparity in hand (largest d/s) is halved again while its width allows (the disparity rule
gives way first: it is a precision margin, the width rule a visibility floor), until the budget holds;
if it still does not, the farthest regions are left out (as `max_regions` does), so it always holds.

A region at scale s > 1 is matched on its strip of the pair shrunk s times (area average) over its window
÷ s and brought back to full resolution: each working pixel's disparity × s on its s×s block
(`match_region`). The working grid is aligned to multiples of s in full-resolution pixels, so the later
stages can take one pixel of each block (`on_working_grid`). What a branch's pixels were matched at is
kept per pixel (`CoarseToFineResult.working_scale`): its cut point's fit and refinement run on that grid
(their cost bounded with the regions'), and its result says so (`Branch.disparity_scale`): the MAVLink
covariance and the cut point's depth-precision score then take the disparity noise in working pixels
(s full-resolution pixels each). The trunk, which has no fine pass, can be fitted on the coarse pass on at most
`roi.budget_trunk_points` of its pixels (`CoarseTrunk.fit`; set in the HD720 deploy file): near the tree its
mask is ~4× what it is at 3 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Protocol

import cv2
import numpy as np

from branchrange.core.masks import BranchMasks

#: SGBM searches disparities in whole steps of this many pixels (a window's cost follows the rounded count).
DISPARITY_STEP = 16
#: Rows of context (px at the working scale) kept above and below a scaled region's box for the SGM paths.
STRIP_CONTEXT_PX = 16


class BudgetSettings(Protocol):
    """The budget's keys of `[roi]` (`branchrange.core.roi.RoiConfig` has them; the roi module builds on this one,
    so the budget names what it reads rather than importing the section)."""

    @property
    def budget(self) -> bool: ...
    @property
    def budget_min_disparity_px(self) -> float: ...
    @property
    def budget_min_diameter_px(self) -> float: ...
    @property
    def budget_max_scale(self) -> int: ...
    @property
    def budget_max_pixels(self) -> int: ...
    @property
    def budget_max_cost_mpd(self) -> float: ...


@dataclass(frozen=True)
class RegionNeed:
    """What decides one region's working scale: the branch's median disparity `disparity_px` and mean width
    `width_px` (both at full resolution, 0 when unknown)."""

    disparity_px: float
    width_px: float


def working_scale(need: RegionNeed, config: BudgetSettings) -> int:
    """The largest power of two s ≤ `budget_max_scale` with need.disparity_px / s ≥ `budget_min_disparity_px`
    and need.width_px / s ≥ `budget_min_diameter_px` (module docstring); 1 when the budget is off."""
    scale = 1
    if not config.budget:
        return scale
    while (
        2 * scale <= config.budget_max_scale
        and need.disparity_px / (2 * scale) >= config.budget_min_disparity_px
        and need.width_px / (2 * scale) >= config.budget_min_diameter_px
    ):
        scale *= 2
    return scale


def scaled_window(d_min: int, d_range: int, scale: int) -> tuple[int, int]:
    """(d_min, d_range) px at the working scale covering the full-resolution window [d_min, d_min + d_range)."""
    low = d_min // scale
    return low, max(1, math.ceil((d_min + d_range) / scale) - low)


def region_cost(box: tuple[int, int, int, int], d_min: int, d_range: int, scale: int) -> tuple[int, int]:
    """(pixels, pixel-disparities) a region costs at `scale`: its box's working pixels, and those times the
    disparities searched (in SGBM's whole steps)."""
    x0, y0, x1, y1 = box
    pixels = math.ceil((x1 - x0) / scale) * math.ceil((y1 - y0) / scale)
    searched = DISPARITY_STEP * math.ceil(scaled_window(d_min, d_range, scale)[1] / DISPARITY_STEP)
    return pixels, pixels * searched


def region_needs(
    regions: list[Any], instances: BranchMasks, coarse_labels: np.ndarray, coarse_disparity: np.ndarray, scale: int
) -> list[RegionNeed]:
    """Each region's `RegionNeed`: the median of its instance's valid coarse disparities (`float32 h×w` px
    under `coarse_labels`, read inside its box ÷ `scale`) × `scale`, and the instance's pixels over its box
    diagonal (full resolution)."""
    index = instances.index
    needs = []
    for region in regions:
        x0, y0, x1, y1 = region.box
        box = (slice(y0 // scale, -(-y1 // scale)), slice(x0 // scale, -(-x1 // scale)))
        values = coarse_disparity[box][(coarse_labels[box] == region.instance_id) & (coarse_disparity[box] > 0)]
        disparity = float(np.median(values)) * scale if values.size else 0.0
        at = int(np.searchsorted(index.ids, region.instance_id))
        width = 0.0
        if at < index.ids.size and index.ids[at] == region.instance_id:
            r0, r1, c0, c1 = (int(v) for v in index.boxes[at])
            width = float(index.counts[at]) / math.hypot(r1 - r0, c1 - c0)
        needs.append(RegionNeed(disparity, width))
    return needs


def fit_budget(regions: list[Any], needs: list[RegionNeed], config: BudgetSettings) -> list[Any]:
    """`regions` (`roi.Region`s) with their working `scale` set by the rule, then within the frame's budget
    (module docstring): further halved nearest-first, then the farthest left out. Order is kept."""
    scales = [working_scale(need, config) for need in needs]
    if not config.budget:
        return [replace(r, scale=1) for r in regions]

    def totals(kept: list[int]) -> tuple[int, int]:
        costs = [region_cost(regions[i].box, regions[i].d_min, regions[i].d_range, scales[i]) for i in kept]
        return sum(c[0] for c in costs), sum(c[1] for c in costs)

    def within(kept: list[int]) -> bool:
        pixels, matching = totals(kept)
        return pixels <= config.budget_max_pixels and matching <= config.budget_max_cost_mpd * 1e6

    kept = list(range(len(regions)))
    while not within(kept):
        can = [
            i
            for i in kept
            if 2 * scales[i] <= config.budget_max_scale
            and needs[i].width_px / (2 * scales[i]) >= config.budget_min_diameter_px
        ]
        if not can:
            break
        scales[max(can, key=lambda i: needs[i].disparity_px / scales[i])] *= 2
    while kept and not within(kept):
        kept.remove(min(kept, key=lambda i: needs[i].disparity_px))
    return [replace(regions[i], scale=scales[i]) for i in kept]


def match_region(backend: Any, left: np.ndarray, right: np.ndarray, region: Any) -> tuple[np.ndarray, np.ndarray]:
    """(disparity `float32 h×w` px at full resolution, 0 invalid; confidence `h×w`) of `region`'s box
    (`roi.Region`) matched by `backend.compute_roi` at the region's working scale (module docstring)."""
    x0, y0, x1, y1 = region.box
    scale = region.scale
    if scale == 1:
        result = backend.compute_roi(left, right, region.box, region.d_min, region.d_range)
        return result.disparity, result.confidence
    height, width = left.shape[:2]
    top = max(0, (y0 - STRIP_CONTEXT_PX * scale) // scale * scale)
    bottom = top + (min(height, y1 + STRIP_CONTEXT_PX * scale) - top) // scale * scale
    columns = width // scale * scale
    size = (columns // scale, (bottom - top) // scale)
    small_left, small_right = (
        cv2.resize(image[top:bottom, :columns], size, interpolation=cv2.INTER_AREA) for image in (left, right)
    )
    box = (x0 // scale, (y0 - top) // scale, min(size[0], -(-x1 // scale)), min(size[1], -(-(y1 - top) // scale)))
    d_min, d_range = scaled_window(region.d_min, region.d_range, scale)
    result = backend.compute_roi(small_left, small_right, box, d_min, d_range)
    up_disparity, up_confidence = (
        np.repeat(np.repeat(values, scale, axis=0), scale, axis=1)
        for values in (result.disparity * np.float32(scale), result.confidence)
    )
    disparity = np.zeros((y1 - y0, x1 - x0), np.float32)
    confidence = np.zeros((y1 - y0, x1 - x0), np.float32)
    row, col = y0 - (top + box[1] * scale), x0 - box[0] * scale  # the box's corner inside the blocks
    rows = min(y1 - y0, up_disparity.shape[0] - row)
    cols = min(x1 - x0, up_disparity.shape[1] - col)
    disparity[:rows, :cols] = up_disparity[row : row + rows, col : col + cols]
    confidence[:rows, :cols] = up_confidence[row : row + rows, col : col + cols]
    return disparity, confidence


def branch_scales(masks: BranchMasks, working: np.ndarray | None) -> dict[int, int]:
    """Each branch's working scale: the largest scale (`uint8 H×W`, `CoarseToFineResult.working_scale`) held by
    at least half of its pixels (a branch whose pixels came from two regions is taken at the coarser one only
    when most of it is); branches at full resolution are left out. Empty without a map."""
    if working is None:
        return {}
    scales = {}
    for instance in masks.branch_ids():
        crop = masks.crop(instance, margin=0)
        if crop is None:
            continue
        rows, cols = crop.pixels()
        values = working[rows, cols]
        for scale in sorted({int(v) for v in np.unique(values)} - {0, 1}, reverse=True):
            if np.count_nonzero(values >= scale) * 2 >= values.size:
                scales[instance] = scale
                break
    return scales


def on_working_grid(rows: np.ndarray, cols: np.ndarray, scale: int, minimum: int = 1) -> np.ndarray:
    """Boolean mask of the pixels (`rows`, `cols`, full resolution) that are one per working pixel at `scale`
    (the top-left of each s×s block): a scaled region's s² copies of one disparity count once. All of them
    when fewer than `minimum` lie on the grid (a small piece of a branch: its few pixels are all the evidence)."""
    on_grid: np.ndarray = (rows % scale == 0) & (cols % scale == 0)
    if scale <= 1 or np.count_nonzero(on_grid) < minimum:
        return np.ones(rows.shape, dtype=bool)
    return on_grid
