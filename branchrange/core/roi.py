"""Coarse-to-fine stereo: find the branches cheaply, then match each one only where and as far as it is.

The application knows what it looks for. A whole frame at full resolution and a full disparity
range costs W·H·D; the branches fill a small part of the frame and each lies within a narrow band
of disparities. So, per frame:
1. **coarse pass** — the pair at `coarse_width` px wide (640 for HD720, scale s = 2), matched by
   SGBM over `max_disp / s` disparities: the whole scene, cheaply;
2. **instances** — the given mask (full resolution; its ids are looked up at coarse resolution), or
   the segmenter run on the coarse disparity;
3. **regions** — per branch, its full-resolution box (+ `box_margin_px`) and its disparity window:
   the 2nd–98th percentile of its coarse disparities × s, ± `window_margin_px`. A branch without
   coarse evidence (thinner than a coarse pixel) is searched over the whole range in its box;
4. **fine pass** — the backend's `compute_roi` on each box over its window (SGBM with a
   `minDisparity` offset; EMCStereo on the left box and the right box shifted by the window start);
5. **composition** — the boxes' disparities in one full-resolution map, zero elsewhere; a box writes
   its own branch's pixels and the background around it (boxes overlap where branches meet).
The trunk is not matched again: it is thick, and its only use is the cylinder that fixes where each
branch leaves it, so that cylinder is fitted on the coarse pass (`CoarseTrunk`, in the geometry
half) and the full-resolution map carries the trunk's coarse disparity (× s) on every s-th pixel of
its mask, for viewers. It was the largest region by far (a whole frame's height near the tree).
A segmenter's coarse labels are brought to full resolution (nearest); a branch's are kept where the
fine disparity lies in its window, so silhouettes (and diameters) are full-resolution ones.
Cut points then come from full-resolution disparity only (the base, where it meets the trunk,
from the trunk's coarse cylinder).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from branchrange.core.cutpoints import CutPointConfig, TrunkModel, fit_trunk
from branchrange.core.geometry import StereoGeometry
from branchrange.core.masks import BranchMasks, MaskCrop
from branchrange.core.region_budget import fit_budget, match_region, region_needs
from branchrange.core.settings_check import Checks, ConfigError, Limit, Settings
from branchrange.core.timing import lap_ms


@dataclass(frozen=True)
class RoiConfig(Settings):
    """The coarse-to-fine settings of `stereo.mode = "roi"` (`branchrange.core.roi`; px at full resolution).

    - `coarse_width`: width of the coarse pass in px (frames narrower than 1.5× this are matched
      coarsely at full resolution, scale 1).
    - `box_margin_px`: how far each instance's box grows on every side (the matcher's block and the
      silhouette's edges need context).
    - `window_margin_px`: how far the disparity window grows beyond the instance's coarse range.
    - `max_regions`: only the nearest this many branches (by coarse disparity) get a fine pass
      (the trunk keeps its coarse disparity); the others are dropped. A bound on a pathological frame,
      not a budget: an SGBM region costs ~1–2 ms, and the learned segmenter gives more than 12 instances
      (fragments and doubtful pieces too) in a quarter of the calibration frames and up to 38 — with 12
      (the setting until 2026-11-26) the pipeline at HD720 lost 7–12 points of recall (benchmarks/RESULTS.md).
    - `network_regions`: with a network backend (emcstereo), only the nearest this many regions —
      the target's candidates — are matched by the network, the others by SGBM (a network region
      costs about 0.4 s at 200×200 px on 2 CPU cores); 0: every region by the network.
    - `full_resolution_instances`: with the learned segmenter, once the regions are matched its instance
      step runs again at full resolution (`LearnedSegmenter.instances`: the coarse look's class
      probabilities brought to full resolution, each branch's fine disparity, the coarse one around it),
      so branches are cut apart at full-resolution depth jumps and their silhouettes are full-resolution
      ones; off = the coarse instances brought up (`roi.refine_labels`). The network still runs once, on the
      coarse frame. On 240 held-out scenes at HD720 recall within 5 cm 65 → 68 % looking once and 70 → 76 %
      with the default second look; on the synthetic HD720 flight (2 cores, one look) a target in 97–100
      instead of 80–85 % of the frames, for ~42 ms a frame on the stereo thread: 5.6–6.1 instead of 8.7–9.6
      fresh results a second (benchmarks/RESULTS.md).
    - `keyframe_interval_s`: with the segmenter (no masks given), run it on keyframes only, this far apart
      (s), and carry each branch's mask over to the frames between by image alignment
      (`branchrange.core.keyframes`); 0: the segmenter on every frame.
    - `track_search_px`: how far (px at full resolution) a carried branch is searched from where it was.
    - `track_min_ncc`: the image match's score (normalised cross-correlation) a carried branch needs;
      under it the branch is lost and the next frame is a keyframe.
    - `track_min_support`: the share of a carried branch's pixels the new frame's disparity must keep (within
      its window); under it the branch was carried to the wrong place: left out, and a keyframe is due.
    - `track_gate_px`: how far (px) a carried branch's disparity may move from the range its pixels had in
      the last frame (median ± 3 robust σ) before the search window's margin: one frame's motion near the tree.
    - `track_max_jump_m`: a carried branch's cut point more than this far (m, camera frame) from its own in
      the last frame is dropped and a keyframe is due: a carried mask that slid onto other pixels (a
      silhouette with much background, the fit taking the background's depth) gives a cut point far off,
      and a tracked result must never jump (one frame's motion at 0.8 m/s moves it 5 cm).
    - `budget`: the region budget (`branchrange.core.region_budget`): each branch's region is matched at the
      coarsest working scale (1, 2, 4 … times smaller) its cut point can afford, and the frame's regions within
      the two caps below; false: every region at full resolution.
    - `budget_min_disparity_px`: a region is shrunk only while its branch's disparity at the working scale stays
      ≥ this (px): relative depth precision σ_d/d at least that of a full-resolution branch at this disparity
      (16 px at HD720 with the ZED Mini is ~2.5 m; regions shrink from ~1.3 m in).
    - `budget_min_diameter_px`: … and while the branch's width at the working scale stays ≥ this (px): a stem the
      matcher still sees (this one is never relaxed to meet the caps).
    - `budget_max_scale`: the coarsest working scale (a power of two; 1: the budget never shrinks a region).
    - `budget_max_pixels`: the frame's region pixels at their working scales at most (px); over it, regions are
      shrunk further nearest-first (the disparity rule gives way, the width rule does not), then the farthest
      are left out. 120,000: above every frame of the rendered HD720 approaches under the two rules (p95 100k,
      max 112k; 156k before the budget), so it bounds a pathological frame (a dense tree close up) and
      never costs a branch on those.
    - `budget_max_cost_mpd`: the frame's matching cost at most, in million pixel-disparities (Σ region pixels ×
      disparities searched, at the working scales): SGBM's time is proportional to it. 6: the same approaches
      need at most 4.75 (p95 4.2; 9.1 before the budget).
    - `budget_trunk_points`: the trunk's cylinder (fitted on the coarse pass) takes at most about this many of its
      pixels (every k-th); 0 (the default): all of them. Its mask grows from ~11,000 coarse px at 3 m to ~41,000
      at 0.8 m at HD720, so deploy/onboard_cpu.toml sets 12,000: near the tree it is fitted on as many points
      as at the start of the approach, each with far less depth noise (the same cut points, the stage flat).
      The count depends on the coarse pass's size, hence no default for every camera.
    - `keyframe_worker`: run the keyframes' segmenter in its own worker (`branchrange.core.keyframe_worker`):
      the stereo thread never waits for it and carries its instances, a few frames old when they arrive, to
      its newest frame; false: a keyframe runs on the stereo thread (as slow as a frame without keyframes).
      Experimental, not for flight: on a quiet 2-core machine its keyframes arrived 0.6–0.9 s old and 10 %
      (0.3 m/s approach) to 38 % (0.8 m/s with 20 °/s yaw) of its targets were false
      (`benchmarks/results/realtime.md`, 2026-11-28 22:05).
    - `track_max_age_s`: with the worker, a track whose keyframe is older than this (s) is dropped (the
      worker is slow, failed or being restarted): its branch goes unreported rather than guessed.
    """

    section = "roi"
    error = ConfigError
    limits = {
        "coarse_width": Limit(minimum=64, expected="at least 64 px"),
        "box_margin_px": Limit(minimum=0, maximum=256, expected="0..256 px"),
        "window_margin_px": Limit(minimum=0, maximum=64, expected="0..64 px"),
        "max_regions": Limit(minimum=1, maximum=256, expected="1..256"),
        "network_regions": Limit(minimum=0, maximum=256, expected="0..256 (0: all)"),
        "keyframe_interval_s": Limit(minimum=0, maximum=10, expected="seconds in [0, 10] (0: every frame)"),
        "track_search_px": Limit(minimum=1, maximum=256, expected="1..256 px"),
        "track_min_ncc": Limit(minimum=-1, maximum=1, expected="a score in [-1, 1]"),
        "track_min_support": Limit(minimum=0, maximum=1, expected="a share in [0, 1]"),
        "track_gate_px": Limit(minimum=0, maximum=64, expected="px in [0, 64]"),
        "track_max_jump_m": Limit(exclusive_minimum=0, expected="metres > 0"),
        "budget_min_disparity_px": Limit(minimum=1, maximum=256, expected="px in [1, 256]"),
        "budget_min_diameter_px": Limit(minimum=1, maximum=64, expected="px in [1, 64]"),
        "budget_max_scale": Limit(minimum=1, maximum=8),
        "budget_max_pixels": Limit(minimum=1000, expected="at least 1000 px"),
        "budget_max_cost_mpd": Limit(exclusive_minimum=0, expected="million pixel-disparities > 0"),
        "budget_trunk_points": Limit(minimum=0, expected="a count ≥ 0 (0: every pixel)"),
        "track_max_age_s": Limit(exclusive_minimum=0, maximum=10, expected="seconds in (0, 10]"),
    }

    coarse_width: int = 640
    box_margin_px: int = 16
    window_margin_px: int = 8
    max_regions: int = 48
    network_regions: int = 1
    full_resolution_instances: bool = True
    keyframe_interval_s: float = 0.0
    track_search_px: int = 32
    track_min_ncc: float = 0.6
    track_min_support: float = 0.5
    track_gate_px: float = 2.0
    track_max_jump_m: float = 0.1
    budget: bool = True
    budget_min_disparity_px: float = 16.0
    budget_min_diameter_px: float = 4.0
    budget_max_scale: int = 4
    budget_max_pixels: int = 120_000
    budget_max_cost_mpd: float = 6.0
    budget_trunk_points: int = 0
    keyframe_worker: bool = False
    track_max_age_s: float = 0.5

    def checks(self) -> Checks:
        """The rules beyond each key's `Limit`."""
        return {
            "budget_max_scale": (self.budget_max_scale in (1, 2, 4, 8), "1, 2, 4 or 8"),
        }


#: SGBM searches disparities in steps of this many pixels.
DISPARITY_STEP = 16
#: Fewest coarse disparities an instance needs for its window to come from them.
MIN_WINDOW_EVIDENCE = 5


@dataclass(frozen=True)
class Region:
    """One instance's fine pass: `box` = (x0, y0, x1, y1) px at full resolution (exclusive ends);
    absolute disparities searched: [d_min, d_min + d_range) px at full resolution; `scale`: the working
    scale it is matched at (`region_budget`: the pair shrunk this many times; 1 = full resolution)."""

    instance_id: int
    box: tuple[int, int, int, int]
    d_min: int
    d_range: int
    backend: str = ""  # the backend that matched it (set when it was matched)
    scale: int = 1

    @property
    def pixels(self) -> int:
        x0, y0, x1, y1 = self.box
        return (x1 - x0) * (y1 - y0)


@dataclass(frozen=True, eq=False)
class CoarseTrunk:
    """The trunk as the coarse pass saw it: its mask (`crop`), the coarse disparity (`float32 h×w` px)
    and camera. Its cylinder (`fit`, in metres like a full-resolution fit) fixes where each branch
    leaves it; from the coarse pass it costs a quarter, and the trunk is thick enough not to need more.
    The geometry half fits it, so the stereo half (the slower one) does not carry it."""

    crop: MaskCrop
    disparity: np.ndarray
    geometry: StereoGeometry
    max_disparity: int

    def fit(self, config: CutPointConfig, max_points: int = 0) -> TrunkModel | None:
        """Its cylinder; on about `max_points` of its pixels at most when > 0 (`RoiConfig.budget_trunk_points`)."""
        return fit_trunk(self.crop, self.disparity, self.geometry, config, self.max_disparity, max_points)


@dataclass(frozen=True, eq=False)
class CoarseToFineResult:
    """Full-resolution `disparity` (`float32 H×W` px, 0 outside the regions), `confidence` (`H×W`),
    the instances used (`masks`), the `regions` matched, the trunk as the coarse pass saw it (None
    without a trunk), the stage times in ms, and `working_scale` (`uint8 H×W`): the scale each pixel's
    fine disparity was matched at (`region_budget`; 1 elsewhere)."""

    disparity: np.ndarray
    confidence: np.ndarray
    masks: BranchMasks | None
    regions: list[Region]
    trunk: CoarseTrunk | None
    timing_ms: dict[str, float]
    working_scale: np.ndarray | None = None


def coarse_scale(width: int, coarse_width: int) -> int:
    """The integer down-scaling factor of the coarse pass: 1 when the frame is already small."""
    return max(1, int(round(width / coarse_width))) if width >= 1.5 * coarse_width else 1


def scaled_geometry(geometry: StereoGeometry, scale: int) -> StereoGeometry:
    """The camera of an image shrunk `scale` times (pixel centres kept: c' = (c + ½) / s − ½)."""
    return StereoGeometry(
        geometry.focal_px / scale,
        geometry.baseline_m,
        (geometry.cx + 0.5) / scale - 0.5,
        (geometry.cy + 0.5) / scale - 0.5,
    )


def disparity_window(coarse_disparities: np.ndarray, scale: int, margin_px: int, max_disp: int) -> tuple[int, int]:
    """(d_min, d_range) at full resolution from an instance's valid coarse disparities (px at coarse scale).

    The 2nd–98th percentile (a few background pixels at the silhouette do not widen it) × scale,
    ± `margin_px`, in whole steps of `DISPARITY_STEP` within [0, max_disp). Without enough evidence:
    the whole range.
    """
    if coarse_disparities.size < MIN_WINDOW_EVIDENCE:
        return 0, max_disp
    low, high = np.percentile(coarse_disparities, [2.0, 98.0]) * scale
    return window_between(float(low), float(high), margin_px, max_disp)


def window_between(low: float, high: float, margin_px: int, max_disp: int) -> tuple[int, int]:
    """(d_min, d_range) px covering disparities [`low`, `high`] ± `margin_px`, in whole steps of
    `DISPARITY_STEP` within [0, max_disp)."""
    d_min = max(0, int(math.floor(low - margin_px)))
    d_max = min(max_disp, int(math.ceil(high + margin_px)))
    d_range = DISPARITY_STEP * max(1, math.ceil((d_max - d_min) / DISPARITY_STEP))
    d_min = max(0, min(d_min, max_disp - d_range))
    return d_min, min(d_range, max_disp)


def plan_regions(
    instances: BranchMasks,
    labels_coarse: np.ndarray,
    coarse_disparity: np.ndarray,
    scale: int,
    config: RoiConfig,
    max_disp: int,
    gates: Mapping[int, tuple[float, float]] | None = None,
) -> list[Region]:
    """A `Region` per branch of `instances` (full resolution): its box grown by the margin, its
    disparity window from the coarse disparities (`float32 h×w` px, 0 invalid) under its coarse
    labels — or, for a branch carried over from the last frame, around the range its own pixels had
    there (`gates`: id → [low, high) px, `branch_gates`), so that the new disparity must agree with the
    branch's, not with whatever it was carried onto. When more than `max_regions` branches are present,
    the nearest ones (largest median coarse disparity) are kept."""
    height, width = instances.shape
    regions, nearness = [], []
    m = config.box_margin_px
    for instance in instances.branch_ids():
        row0, row1, col0, col1 = instances.index.box(instance)  # type: ignore[misc]  # ids come from the index
        values = coarse_disparity[(labels_coarse == instance) & (coarse_disparity > 0)]
        if gates is not None and instance in gates:
            d_min, d_range = window_between(*gates[instance], config.window_margin_px, max_disp)
        else:
            d_min, d_range = disparity_window(values, scale, config.window_margin_px, max_disp)
        box = (max(0, col0 - m), max(0, row0 - m), min(width, col1 + m), min(height, row1 + m))
        regions.append(Region(int(instance), box, d_min, d_range))
        nearness.append(float(np.median(values)) if values.size else 0.0)
    if len(regions) > config.max_regions:
        order = sorted(range(len(regions)), key=lambda i: -nearness[i])[: config.max_regions]
        regions = [regions[i] for i in sorted(order)]
    return regions


def branch_gates(masks: BranchMasks, disparity: np.ndarray, margin_px: float) -> dict[int, tuple[float, float]]:
    """Each branch's own disparity range [low, high) px at full resolution, from its pixels' valid
    `float32 H×W` disparity: what the next frame's carried-over mask must agree with (a branch moves
    little in depth from one frame to the next). The median ± 3 robust σ (1.4826 · MAD) ± `margin_px`
    (the depth change of a frame's motion): a silhouette's edge pixels that read the background (up to a
    fifth of a thin stem's) must not widen it to the background's depth, or the carried mask would keep
    background pixels and its cut point would go there. A branch with too little depth is left out."""
    gates = {}
    for instance in masks.branch_ids():
        crop = masks.crop(instance, margin=0)
        assert crop is not None, "every id of branch_ids() has pixels, hence a crop"
        rows, cols = crop.pixels()
        values = disparity[rows, cols]
        values = values[values > 0]
        if values.size < MIN_WINDOW_EVIDENCE:
            continue
        median = float(np.median(values))
        spread = 3.0 * 1.4826 * float(np.median(np.abs(values - median))) + margin_px
        gates[instance] = (max(0.0, median - spread), median + spread)
    return gates


def refine_labels(
    labels: np.ndarray, scale: int, disparity: np.ndarray, regions: list[Region], trunk_id: int | None
) -> np.ndarray:
    """Full-resolution labels (`int32 H×W`) from up-sampled coarse ones (`labels`, nearest): each
    branch grown by one coarse pixel into the background and kept where the fine disparity lies in
    its window; the trunk as it is (it has no fine pass)."""
    kernel = np.ones((2 * scale + 1, 2 * scale + 1), np.uint8)
    refined = np.zeros_like(labels)
    if trunk_id is not None:
        refined[labels == trunk_id] = trunk_id
    for region in regions:
        x0, y0, x1, y1 = region.box
        box_labels = labels[y0:y1, x0:x1]
        grown = cv2.dilate((box_labels == region.instance_id).astype(np.uint8), kernel).astype(bool)
        grown &= (box_labels == region.instance_id) | (box_labels == 0)
        d = disparity[y0:y1, x0:x1]
        inside = grown & (d >= region.d_min) & (d < region.d_min + region.d_range) & (d > 0)
        refined[y0:y1, x0:x1][inside] = region.instance_id
    return refined


def trunk_from_coarse(
    disparity: np.ndarray, confidence: np.ndarray, labels: np.ndarray, trunk_id: int | None, coarse: Any, scale: int
) -> None:
    """Write the trunk's coarse disparity (× `scale`, full-resolution px) and confidence into the full-
    resolution maps, in place, on every `scale`-th pixel (rows and columns) of its full-resolution mask."""
    if trunk_id is None:
        return
    offset = scale // 2
    rows = min(coarse.disparity.shape[0], len(range(offset, labels.shape[0], scale)))
    cols = min(coarse.disparity.shape[1], len(range(offset, labels.shape[1], scale)))
    grid = (slice(offset, offset + rows * scale, scale), slice(offset, offset + cols * scale, scale))
    trunk = labels[grid] == trunk_id
    disparity[grid][trunk] = coarse.disparity[:rows, :cols][trunk] * scale
    confidence[grid][trunk] = coarse.confidence[:rows, :cols][trunk]


def on_coarse_grid(labels: np.ndarray, scale: int, size: tuple[int, int]) -> np.ndarray:
    """Full-resolution `labels` (`H×W`) read at the coarse pass's pixel centres (every `scale`-th pixel, offset
    `scale // 2`), cut to the coarse frame's `size` = (w, h)."""
    return labels[scale // 2 :: scale, scale // 2 :: scale][: size[1], : size[0]]


def finest_disparity(fine: np.ndarray, coarse: np.ndarray, scale: int) -> np.ndarray:
    """`float32 H×W` px: the fine disparity where the regions found one, elsewhere the coarse disparity (`h×w`
    px at coarse scale) brought to full resolution (nearest, × `scale`) — what the instance step sees when
    it runs again at full resolution: each branch's own matching, and the trunk and background around it."""
    height, width = fine.shape
    coarse_full = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_NEAREST) * np.float32(scale)
    return np.where(fine > 0, fine, coarse_full).astype(np.float32)


def coarse_trunk(
    coarse_labels: np.ndarray, trunk_id: int | None, disparity: np.ndarray, geometry: StereoGeometry, max_disparity: int
) -> CoarseTrunk | None:
    """The trunk of `coarse_labels` (`int32 h×w`, its id `trunk_id`) as a `CoarseTrunk` on the coarse `disparity`
    with the coarse camera `geometry`; None without one."""
    crop = BranchMasks(coarse_labels, trunk_id).trunk_crop() if trunk_id is not None else None
    return None if crop is None else CoarseTrunk(crop, disparity, geometry, max_disparity)


class CoarseToFine:
    """The `roi` mode's stereo: see the module docstring.

    `fine_backend` needs `compute_roi(left, right, roi, d_min, d_range)` (`stereo.backends`);
    the coarse pass is always SGBM (an EMCStereo coarse pass would cost more than it saves).
    `segmenter` finds instances at coarse resolution when a frame comes without a mask.
    """

    def __init__(self, config: RoiConfig, fine_backend: Any, segmenter: Any, max_disp: int) -> None:
        if not hasattr(fine_backend, "compute_roi"):
            raise ValueError(
                f"stereo backend {getattr(fine_backend, 'name', fine_backend)!r} cannot match regions "
                "of interest; use mode = 'full' with it"
            )
        self.config = config
        self.fine = fine_backend
        self.segmenter = segmenter
        self.max_disp = int(max_disp)
        self._sgbm_backends: dict[
            int, Any
        ] = {}  # SGBM backends by max_disp (coarse pass, regions beyond network_regions)

    def _sgbm(self, max_disp: int) -> Any:
        """An SGBM backend for `max_disp` (coarse pass, or regions beyond `network_regions`), built once."""
        if max_disp not in self._sgbm_backends:
            from stereo.backends import make_backend

            self._sgbm_backends[max_disp] = make_backend("sgbm", max_disp=max_disp)
        return self._sgbm_backends[max_disp]

    def _matchers(self, regions: list[Region]) -> list[Any]:
        """The backend for each region: the fine backend for all when it is SGBM, else for the nearest
        `network_regions` (largest window centre; 0: all) and SGBM for the rest."""
        if self.fine.name == "sgbm":
            return [self.fine] * len(regions)
        sgbm = self._sgbm(self.max_disp)
        limit = self.config.network_regions
        nearest = sorted(range(len(regions)), key=lambda i: -(regions[i].d_min + regions[i].d_range / 2))
        chosen = set(nearest if limit == 0 else nearest[:limit])
        return [self.fine if i in chosen else sgbm for i in range(len(regions))]

    def compute(
        self,
        left: np.ndarray,
        right: np.ndarray,
        masks: BranchMasks | None,
        geometry: StereoGeometry,
        *,
        full_resolution_instances: bool = True,
        carried: bool = False,
        gates: Mapping[int, tuple[float, float]] | None = None,
    ) -> CoarseToFineResult:
        """Full-resolution disparity inside each instance's region of a rectified `uint8 H×W×3` pair.

        `full_resolution_instances` False skips that step for this frame even where the settings ask for
        it (the daemon's load shedding). `carried`: `masks` were carried over from the last frame
        (`branch_propagation`), not measured: each branch is then matched around `gates` (its own
        disparity range in the last frame, `branch_gates`) and, like a segmenter's, kept where the fine
        disparity lies in that search window (`refine_labels`)."""
        timing: dict[str, float] = {}
        t = time.perf_counter()
        height, width = left.shape[:2]
        scale = coarse_scale(width, self.config.coarse_width)
        small = (width // scale, height // scale)
        coarse_max = DISPARITY_STEP * max(1, math.ceil(self.max_disp / scale / DISPARITY_STEP))
        if scale > 1:
            left_small = cv2.resize(left, small, interpolation=cv2.INTER_AREA)
            right_small = cv2.resize(right, small, interpolation=cv2.INTER_AREA)
        else:
            left_small, right_small = left, right
        coarse = self._sgbm(coarse_max).compute(left_small, right_small)
        t = lap_ms(timing, "coarse_stereo", t)
        coarse_logits = None  # the network's look at the coarse frame, when its instances are found again
        small_geometry = scaled_geometry(geometry, scale)
        if masks is None:
            refind = self.config.full_resolution_instances and full_resolution_instances
            if refind and scale > 1 and hasattr(self.segmenter, "instances"):
                coarse_logits, ood = self.segmenter.looked(left_small, coarse.disparity)
                found = self.segmenter.instances(coarse_logits, left_small, coarse.disparity, small_geometry, ood=ood)
            else:
                found = self.segmenter.segment(left_small, coarse.disparity, small_geometry, coarse.confidence)
            coarse_labels = found.labels
            labels_full = cv2.resize(coarse_labels.astype(np.int32), (width, height), interpolation=cv2.INTER_NEAREST)
            instances = replace(found, labels=labels_full)
        else:
            instances = masks
            coarse_labels = on_coarse_grid(masks.labels, scale, small)
            labels_full = masks.labels
        t = lap_ms(timing, "segment", t)
        regions = plan_regions(
            instances, coarse_labels, coarse.disparity, scale, self.config, self.max_disp, gates if carried else None
        )
        regions = fit_budget(
            regions, region_needs(regions, instances, coarse_labels, coarse.disparity, scale), self.config
        )
        disparity = np.zeros((height, width), np.float32)
        confidence = np.zeros((height, width), np.float32)
        working = np.ones((height, width), np.uint8)
        matchers = self._matchers(regions)
        regions = [replace(region, backend=backend.name) for region, backend in zip(regions, matchers)]
        for region, backend in zip(regions, matchers):
            box_disparity, box_confidence = match_region(backend, left, right, region)
            x0, y0, x1, y1 = region.box
            box_labels = labels_full[y0:y1, x0:x1]
            take = ((box_labels == region.instance_id) | (box_labels == 0)) & (box_disparity > 0)
            disparity[y0:y1, x0:x1][take] = box_disparity[take]
            confidence[y0:y1, x0:x1][take] = box_confidence[take]
            working[y0:y1, x0:x1][take] = region.scale
        t = lap_ms(timing, "roi_stereo", t)
        if coarse_logits is not None:
            instances = self.segmenter.instances(
                coarse_logits,
                left,
                finest_disparity(disparity, coarse.disparity, scale),
                geometry,
                instances.light,
                instances.ood,
            )
            labels_full = instances.labels
            coarse_labels = on_coarse_grid(labels_full, scale, small)
            lap_ms(timing, "instances", t)
        elif masks is None or carried:  # carried masks are full-resolution ones already: not grown
            refined = refine_labels(labels_full, 0 if carried else scale, disparity, regions, instances.trunk_id)
            instances = replace(instances, labels=refined)
            lap_ms(timing, "refine", t)
        trunk_from_coarse(disparity, confidence, labels_full, instances.trunk_id, coarse, scale)
        return CoarseToFineResult(
            disparity,
            confidence,
            instances,
            regions,
            coarse_trunk(coarse_labels, instances.trunk_id, coarse.disparity, small_geometry, coarse_max),
            timing,
            working,
        )
