"""Sub-pixel disparity of each branch from its own pixels: the mask-guided photometric refinement.

Why: a block matcher (SGBM, or the coarse pass of the roi mode) compares windows several pixels
wide. Across a stem 2–4 px wide most of such a window is the background behind it, so the stem's
disparity is pulled toward the background's: on the held-out synthetic scenes SGBM's disparity
inside a branch lies a median 0.11 px (p90 0.6 px) from the true one, mostly on the far side, and
at 2–3 m with the ZED Mini at 640×360 (f·B ≈ 22 px·m) every 0.2 px is 5 cm of depth — the whole
tolerance of a cut point.

How: once the masks are known, each branch is matched on its own pixels only. A straight branch
is a 3D line, so its disparity is linear along its image axis, `d(s) = a + b·s` (`s` px along
`silhouette.image_axis`). Starting from a robust line through the given disparity, a 1-D search
over the offset `a` (±`SEARCH_PX`) and Gauss–Newton on (a, b) minimise the capped squared
difference between the left image's mask pixels and the right image sampled at `u − d(s)`
(bilinear along the row). The pixels that had a valid disparity then take the refined line's value
`a + b·s`; holes stay holes, so the valid share still counts in the cut point's confidence. The
block matcher's scatter around the line is dropped from the geometry: it is its window mixing the
background into the stem, not the stem's shape, and it tilted the fitted axis — on calibration
scenes 2861–2940 with SGBM and truth masks, taking the line instead of shifting the scatter by
(a − a₀, b − b₀) raised recall within 5 cm from 71.5 to 74.8 %. The scatter still says how far the
block matcher can be trusted on that branch, which the cut-point fit's residual used to carry into
the confidence: each refined pixel's stereo confidence is scaled by its agreement with the robust
line through the given values (`line_agreement`) — the scatter, not the bias the refinement removed.

When the matcher misses the stem altogether. On a stem 2 px wide the window may see only the
background: the given values are then the background's, many pixels off, or holes, and no search
around them reaches the stem (on calibration scenes 2861–2900, of the branches missed with truth
masks, about a third had a refined line over 1 px from the true one while the photometric cost's
minimum over all shifts lay at the true one). So every branch is also searched over the whole
disparity range (`whole_range_line`: shifts 0..max in ½ px steps and a few slopes, on a sample of its
pixels) and refined from there; that line replaces the matcher's when it matches clearly better and
distinctly (`REPLACE_COST_RATIO`, `REPLACE_MIN_DISTINCTIVENESS`) or the matcher gave none. Its branch
then takes the line at **every** pixel, holes included — the matcher's holes and values there were its
failure, not evidence — and the stereo confidence of those pixels is the match's distinctiveness: how
much better it is than the best rival shift (a stem repeated along the row, or a smooth one, matches
several shifts alike and gets none). Measured with SGBM on the held-out scenes 50000–50029: truth masks
81.1 → 87.2 % within 5 cm, the learned segmenter 57.8 → 59.4 %; cost ≈ 6 ms a 640×360 frame of ~9
branches. A searched line is only as good as the mask: on calibration scenes 2861–2940 the searched
cut points were right 61 % of the time with truth masks but 20 % with the learned segmenter's pieces
(mostly small pieces holding background pixels); the confidence calibration sees them as they are.

A branch is left as it was when its pixels carry no horizontal texture to match (a stem lying
along the rows: the aperture problem), when it has too few pixels, or when no refinement converges
inside its search (no clear minimum). The trunk is never touched: it is wide and its block-matched
disparity is already good.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from branchrange.core.geometry import GeometryError, LinearFit, fit_linear_robust, valid_disparity
from branchrange.core.masks import BranchMasks
from branchrange.core.region_budget import on_working_grid
from branchrange.core.silhouette import image_axis

#: offsets of the initial line searched, ± px, and the search step (px)
SEARCH_PX, SEARCH_STEP_PX = 3.0, 0.25
#: the whole-range search: offset step (px), disparity slopes tried (px per px along the axis, besides
#: the block matcher's own) and the most pixels of a branch it compares (spread along the branch)
WHOLE_RANGE_STEP_PX = 0.5
WHOLE_RANGE_SLOPES = (-0.2, -0.05, 0.0, 0.05, 0.2)
WHOLE_RANGE_PIXELS = 32
#: the searched line replaces the block matcher's when its cost is below this share of the latter's and
#: its match is at least this distinct: a match hardly better than a rival shift is no evidence against
#: the matcher (the demo scene's branch 7, foreshortened toward the camera, was otherwise put 5 cm off)
REPLACE_COST_RATIO, REPLACE_MIN_DISTINCTIVENESS = 0.8, 0.1
#: the offsets within this distance (px) of the best one count as its own valley, not a rival match
RIVAL_PX = 1.0
#: distinctiveness (1 − best cost / best rival's) at which a searched line's filled pixels get full confidence
FULL_DISTINCTIVENESS = 0.5
#: the whole-range search's largest shift (px) when no `max_disparity` is given and the values are smaller
DEFAULT_MAX_SHIFT_PX = 128.0
#: Gauss–Newton iterations at most, and the step (px) below which it has converged
ITERATIONS, CONVERGED_PX = 10, 1e-3
#: grey-level residuals beyond this count as this much (occlusion, specular spots): a capped square
RESIDUAL_CAP = 20.0
#: mean squared horizontal gradient (grey levels² per px²) below which a branch has nothing to match
MIN_MEAN_GRADIENT_SQ = 4.0
#: fewest pixels for a refinement, and fewest with a valid disparity for the block matcher's line
MIN_PIXELS = 6
#: band (px) of the robust initial line through the given disparity
INITIAL_BAND_PX = 1.0
#: a pixel is textured across the rows when its horizontal grey-level step exceeds this
TEXTURE_STEP = 8.0
#: least share of a branch's pixels textured across the rows: below it (a smooth stem lying along
#: the rows, whose only features are its two ends) offset and slope are not determined
MIN_TEXTURED_SHARE = 0.25
#: a pixel whose given disparity lies farther than this (px) from the line through its branch's values
#: does not agree with it. Chosen by the recall at calibrated confidence ≥ 0.8 (fitted on scenes
#: 2861–2920, judged on 2921–2980 and 50000–50029): at 1 px the learned segmenter keeps its 30–34 % of
#: when the scatter itself was fitted, truth masks rise from 31–33 to 39–41 %; at 0.5 px learned falls to 26 %
AGREEMENT_PX = 1.0


@dataclass(frozen=True)
class RefinedBranches:
    """What `refine_branch_disparity` returns: the corrected `disparity` (`float32 H×W` px) and the
    `shifts` applied, one per refined branch."""

    disparity: np.ndarray
    shifts: list[BranchShift]


@dataclass(frozen=True)
class BranchShift:
    """How one branch's disparity moved: by `offset_px` at the pixels' centroid and by `slope_px`
    per px along its image axis, from the matcher's robust line (0 and 0 when it gave none);
    `cost_before` / `cost_after` are the mean capped squared grey-level residuals of its pixels at the
    initial and the refined line; `searched`: the line came from the whole-range search."""

    mask_id: int
    offset_px: float
    slope_px: float
    cost_before: float
    cost_after: float
    searched: bool = False


def grey(image: np.ndarray) -> np.ndarray:
    """`float32 H×W` grey levels (0–255) of an `uint8 H×W×3` RGB or `H×W` grey image."""
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32)
    return image.astype(np.float32)


def _sample_rows(image: np.ndarray, x: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`image` (`H×W`) at sub-pixel columns `x` of integer `rows` (both `(N,)`), linear along the row:
    (values, d(value)/dx, inside the image)."""
    width = image.shape[1]
    inside = (x >= 0) & (x <= width - 1)
    x = np.clip(x, 0.0, width - 1.0 - 1e-6)
    x0 = np.floor(x).astype(np.int64)
    fraction = x - x0
    a, b = image[rows, x0], image[rows, x0 + 1]
    return a + fraction * (b - a), b - a, inside


def _capped_cost(residual: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Mean capped squared residual over the last axis, samples outside the image counting as the cap."""
    squared = np.where(inside, np.minimum(residual * residual, RESIDUAL_CAP**2), RESIDUAL_CAP**2)
    cost: np.ndarray = np.mean(squared, axis=-1)
    return cost


def refine_line(
    left_values: np.ndarray,
    right_grey: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    s: np.ndarray,
    intercept: float,
    slope: float,
) -> tuple[float, float, float, float] | None:
    """The disparity line (a, b) of one branch's pixels that best matches the right image.

    `left_values` `(N,)` grey levels of the pixels at (`rows`, `cols`) `(N,)`, `s` `(N,)` their
    position (px) along the branch's image axis, (`intercept`, `slope`) the initial line in px and
    px/px. Returns (a, b, cost at the initial line, cost at the refined one), or None when the
    pixels carry too little horizontal texture or the best offset lies at the edge of the search.
    """

    def residual(a: np.ndarray | float, b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        values, gradient, inside = _sample_rows(right_grey, cols - (np.asarray(a)[..., None] + b * s), rows)
        return values - left_values, gradient, inside

    offsets = np.arange(-SEARCH_PX, SEARCH_PX + 1e-9, SEARCH_STEP_PX)
    costs = _capped_cost(*residual(intercept + offsets, slope)[::2])  # (offsets,): all lines in one pass
    best = int(np.argmin(costs))
    if best in (0, len(offsets) - 1):
        return None  # no minimum inside the search: the initial line is far off or the match ambiguous
    cost_before = float(costs[int(np.argmin(np.abs(offsets)))])
    a, b = intercept + float(offsets[best]), slope
    for _ in range(ITERATIONS):
        r, gradient, inside = residual(a, b)
        weight = (inside & (np.abs(r) < RESIDUAL_CAP)).astype(np.float64)
        g_w = gradient * weight
        h_aa, h_ab, h_bb = g_w @ gradient, g_w @ (gradient * s), g_w @ (gradient * s * s)
        if h_aa < MIN_MEAN_GRADIENT_SQ * max(1.0, weight.sum()):
            return None  # a stem along the rows: nothing to match across
        # Gauss–Newton on r(a, b) with dr/da = −g, dr/db = −g·s: solve [h_aa h_ab; h_ab h_bb] · step = [Σ g·r, Σ g·s·r]
        j_a, j_b = g_w @ r, g_w @ (r * s)
        determinant = h_aa * h_bb - h_ab * h_ab
        if determinant <= 1e-8 * h_aa * h_bb:  # a branch too short for a slope: keep the initial one
            step = np.array([j_a / h_aa, 0.0])
        else:
            step = np.array([h_bb * j_a - h_ab * j_b, h_aa * j_b - h_ab * j_a]) / determinant
        step = np.clip(step, -0.5, 0.5)  # a linearisation holds for about half a pixel
        a, b = a + float(step[0]), b + float(step[1])
        if abs(step[0]) < CONVERGED_PX:
            break
    if abs(a - intercept) > SEARCH_PX:
        return None
    cost_after = float(_capped_cost(*residual(a, b)[::2]))
    if cost_after > cost_before:
        return None
    return a, b, cost_before, cost_after


def line_agreement(deviation_px: np.ndarray) -> np.ndarray:
    """Factor in [0.5, 1] per pixel, 0 beyond `AGREEMENT_PX`, from how far (px, `(N,)`) its block-matched
    disparity lies from the line through its branch's values: the cut-point fit's inlier share and
    residual penalty (`cutpoints._confidence`: inliers × (1 − ½·residual / band)) applied pixel by pixel."""
    distance = np.abs(deviation_px)
    return np.where(distance <= AGREEMENT_PX, 1.0 - 0.5 * distance / AGREEMENT_PX, 0.0)


@dataclass(frozen=True)
class SearchedLine:
    """The best disparity line of a branch over the whole disparity range: `intercept` (px at s = 0)
    and `slope` (px per px along the axis) as a pixel shift between the views, and how distinct its
    match is: `distinctiveness` = 1 − its cost / the best cost more than `RIVAL_PX` away (0: a rival
    matches as well, 1: nothing else matches at all)."""

    intercept: float
    slope: float
    distinctiveness: float


def whole_range_line(
    left_values: np.ndarray,
    right_grey: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    s: np.ndarray,
    max_shift_px: float,
    slopes: tuple[float, ...],
) -> SearchedLine:
    """The line (a, b) of least capped squared residual over shifts 0..`max_shift_px` (steps of
    `WHOLE_RANGE_STEP_PX`) and the given `slopes`, on at most `WHOLE_RANGE_PIXELS` of the branch's pixels.

    Arguments as for `refine_line`. Why: where the block matcher's window saw mostly the background
    behind a thin stem, its values on the stem are the background's, many pixels off, or holes; a search
    around them cannot reach the stem's own match. The right image is sampled once per pixel at every
    shift the lines can ask for (a table `pixels × shifts`); each line then only looks values up.
    """
    n = rows.size
    pick = np.unique(np.linspace(0, n - 1, min(n, WHOLE_RANGE_PIXELS)).round().astype(np.int64))
    s_pick, step = s[pick], WHOLE_RANGE_STEP_PX
    offsets = np.arange(0.0, max_shift_px + 1e-9, step)
    # a line asks pixel p for the shift a + b·s_p: table columns index shifts from `lowest` in `step`s
    reach = max(abs(b) for b in slopes) * float(np.max(np.abs(s_pick)))
    lowest = -np.ceil(reach / step) * step
    shifts = np.arange(lowest, max_shift_px + reach + step, step)
    values, _, inside = _sample_rows(
        right_grey, (cols[pick, None] - shifts[None, :]).ravel(), np.repeat(rows[pick], shifts.size)
    )
    residual = values.reshape(pick.size, shifts.size) - left_values[pick, None]
    table = np.where(
        inside.reshape(residual.shape) & (shifts >= 0)[None, :],  # the right view never sees a point to the right
        np.minimum(residual * residual, RESIDUAL_CAP**2),
        RESIDUAL_CAP**2,
    )
    first = np.arange(offsets.size)[None, :] - int(round(lowest / step))
    costs_by_slope = [
        np.take_along_axis(
            table, np.clip(first + np.rint(slope * s_pick / step).astype(np.int64)[:, None], 0, shifts.size - 1), axis=1
        ).mean(axis=0)
        for slope in slopes
    ]
    best = int(np.argmin([costs.min() for costs in costs_by_slope]))
    costs, slope = costs_by_slope[best], slopes[best]
    intercept = float(offsets[int(np.argmin(costs))])
    rivals = costs[np.abs(offsets - intercept) > RIVAL_PX]
    distinct = 1.0 - float(costs.min()) / float(rivals.min()) if rivals.size and rivals.min() > 0 else 1.0
    return SearchedLine(intercept, slope, max(0.0, distinct))


@dataclass(frozen=True)
class _BranchLine:
    """The line chosen for one branch: (a, b) as a pixel shift, the costs, and whether it came from the
    whole-range search (the block matcher's values then say nothing about it)."""

    intercept: float
    slope: float
    cost_before: float
    cost_after: float
    searched: SearchedLine | None


def _branch_line(
    left_values: np.ndarray,
    right_grey: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    s: np.ndarray,
    initial: LinearFit | None,
    doffs_px: float,
    max_shift_px: float,
) -> _BranchLine | None:
    """The branch's line: the block matcher's (`initial`, in disparity px) refined, or the whole-range
    search's best refined when the matcher gave none or that matches clearly better — a cost below
    `REPLACE_COST_RATIO` of the other's and a distinct match (`REPLACE_MIN_DISTINCTIVENESS`), not a tie
    broken by noise. None when neither refinement converges.

    Both are refined even when they start in one valley: the search's slope grid can start a long branch
    nearer its own slope (on calibration scenes 2861–2940 with truth masks, recall within 5 cm 79.8 %
    when the matcher's line alone was refined in that case, 81.1 % with both).
    """
    local = None
    if initial is not None:
        local = refine_line(left_values, right_grey, rows, cols, s, initial.intercept - doffs_px, initial.slope)
    slopes = WHOLE_RANGE_SLOPES if initial is None else (*WHOLE_RANGE_SLOPES, initial.slope)
    searched = whole_range_line(left_values, right_grey, rows, cols, s, max_shift_px, slopes)
    local_cost = local[3] if local is not None else np.inf
    found = refine_line(left_values, right_grey, rows, cols, s, searched.intercept, searched.slope)
    distinct = local is None or searched.distinctiveness >= REPLACE_MIN_DISTINCTIVENESS
    if found is not None and found[3] < REPLACE_COST_RATIO * local_cost and distinct:
        cost_before = local[2] if local is not None else found[2]
        return _BranchLine(found[0], found[1], cost_before, found[3], searched)
    return None if local is None else _BranchLine(*local, searched=None)


def refine_branch_disparity(
    left: np.ndarray,
    right: np.ndarray,
    disparity: np.ndarray,
    masks: BranchMasks,
    confidence: np.ndarray | None = None,
    doffs_px: float = 0.0,
    max_disparity: float | None = None,
    working_scales: Mapping[int, int] | None = None,
) -> RefinedBranches:
    """Each branch instance's disparity refined on its own pixels (see the module docstring).

    `left`, `right`: the rectified pair (`uint8 H×W×3` RGB or `H×W` grey); `disparity`: `float32
    H×W` px with 0 where invalid, `doffs_px` already added (Middlebury's offset: the pixel shift
    between the views is `disparity − doffs_px`); `masks`: the frame's instances; `confidence`: the
    stereo confidence `float32 H×W` in [0, 1], or None — changed **in place** on the refined branches
    (the block matcher's scatter, or a searched line's distinctiveness): it is the caller's working
    copy, and a second full-frame array would cost more than the refinement itself (at HD720 its fresh
    pages took 5 ms against 5 ms for all the rest). `max_disparity` (px; None: the largest valid value
    given, at least `DEFAULT_MAX_SHIFT_PX`) bounds the whole-range search. `disparity` is not modified.
    `working_scales`: mask id → the scale its disparity was matched at (`region_budget`): its line is then
    fitted and refined on one pixel per working pixel (`on_working_grid`: the cost bounded with its region's)
    and written to all of its pixels.
    """
    refined = np.array(disparity, dtype=np.float32, copy=True)
    shifts: list[BranchShift] = []
    branch_ids = masks.branch_ids()
    if not branch_ids:
        return RefinedBranches(refined, shifts)
    left_grey, right_grey = grey(left), grey(right)
    last_column = left_grey.shape[1] - 1
    if max_disparity is None:
        given = disparity[valid_disparity(disparity)]
        max_disparity = max(DEFAULT_MAX_SHIFT_PX, float(given.max()) if given.size else 0.0)
    max_shift = max(1.0, max_disparity - doffs_px)
    for mask_id in branch_ids:
        crop = masks.crop(mask_id)
        if crop is None:
            continue
        rows, cols = crop.pixels()
        if rows.size < MIN_PIXELS:
            continue
        horizontal_step = left_grey[rows, np.minimum(cols + 1, last_column)] - left_grey[rows, np.maximum(cols - 1, 0)]
        if np.mean(np.abs(horizontal_step) > TEXTURE_STEP) < MIN_TEXTURED_SHARE:
            continue
        values = disparity[rows, cols].astype(np.float64)
        valid = valid_disparity(values, max_disparity)
        s = image_axis(crop).s
        sub = on_working_grid(rows, cols, (working_scales or {}).get(mask_id, 1), MIN_PIXELS)
        initial = None
        if np.count_nonzero(valid & sub) >= MIN_PIXELS:
            try:
                initial = fit_linear_robust(s[valid & sub], values[valid & sub], INITIAL_BAND_PX, penalty_above=1.0)
            except GeometryError:  # every valid pixel at one position along the axis
                initial = None
        at = (rows[sub], cols[sub])
        line = _branch_line(left_grey[at], right_grey, *at, s[sub], initial, doffs_px, max_shift)
        if line is None:
            continue
        if line.searched is None:  # the matcher's own line, refined: its holes stay holes
            on_line = line.intercept + doffs_px + line.slope * s[valid]
            refined[rows[valid], cols[valid]] = np.maximum(on_line, 1e-3)
            if confidence is not None and initial is not None:  # its scatter; the bias was what was corrected
                scatter = values[valid] - (initial.intercept + initial.slope * s[valid])
                confidence[rows[valid], cols[valid]] *= line_agreement(scatter).astype(np.float32)
        else:  # the matcher missed the stem: its values and holes say nothing, the match is the evidence
            refined[rows, cols] = np.maximum(line.intercept + doffs_px + line.slope * s, 1e-3)
            if confidence is not None:
                confidence[rows, cols] = min(1.0, line.searched.distinctiveness / FULL_DISTINCTIVENESS)
        reference = (
            (initial.intercept, initial.slope) if initial is not None else (line.intercept + doffs_px, line.slope)
        )
        offset, slope = line.intercept + doffs_px - reference[0], line.slope - reference[1]
        shifts.append(BranchShift(mask_id, offset, slope, line.cost_before, line.cost_after, line.searched is not None))
    return RefinedBranches(refined, shifts)
