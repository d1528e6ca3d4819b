"""Cut points of branches: from a disparity map and branch masks to where the pruning tool must go.

Per branch (design.md, Cut points):
1. 3D points from valid disparity inside the slightly eroded mask.
2. The axis: disparity along the silhouette's centreline by a robust line fit (in px), and at
   two stations the perspective-exact cross-section (`branchrange.core.cylinder_section`: the
   silhouette's edges are tangent planes, the mean disparity across sets the distance), so a
   near, thick trunk off the optical axis is fitted on its axis, not beside it. A silhouette
   seen end-on: a robust 3D line (RANSAC + IRLS) through the points, pushed back from the
   visible surface by the expected π/4·r (`surface_correction` switches both corrections).
3. The ends come from the mask in the image (exact where depth is not: near the trunk, depth is
   often occluded), lifted onto the 3D axis. The base is the end meeting the trunk when a trunk is
   known, else the thicker end (for a branch seen end-on, the deeper end).
4. Cut point = base + `cut_offset_m` along the axis toward the tip; distance from the camera;
   diameter = 2·D·sin β from the silhouette's width (D the camera's distance from the axis); confidence ∈ [0, 1]
   from the valid-depth fraction, the fit (inlier share and residual), the stereo confidence and the amount of evidence.
A branch with too little evidence is dropped with a reason, never invented.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from branchrange.core.branch_base import base_cut_by_image_border, base_hidden_by_occluder
from branchrange.core.cylinder_section import cross_section_from_rays, radius_from_silhouette, section_rays
from branchrange.core.geometry import (
    GeometryError,
    Line3D,
    LinearFit,
    StereoGeometry,
    backproject,
    fit_line_robust,
    fit_linear_robust,
    pixel_ray,
    project,
    valid_disparity,
    vector_norm,
)
from branchrange.core.masks import BranchMasks, MaskCrop, as_crop, check_instance_count, erode
from branchrange.core.region_budget import on_working_grid
from branchrange.core.settings_check import Checks, Limit, Settings, in_physical_range
from branchrange.core.silhouette import ImageAxis, WidthProfile, image_axis, width_profile
from stereo.pinhole import depth_from_disparity

TargetPolicy = Literal["nearest_confident", "nearest", "most_confident", "thickest"]
TARGET_POLICIES: tuple[str, ...] = ("nearest_confident", "nearest", "most_confident", "thickest")
#: The target policy unless configured otherwise.
DEFAULT_TARGET_POLICY: TargetPolicy = "nearest_confident"


class CutPointConfigError(ValueError):
    """A cut-point setting out of its range; the message names the key."""


@dataclass(frozen=True)
class CutPointConfig(Settings):
    """`[cutpoints]`: where on a branch the cut goes, which branches are kept and which is the
    target (lengths in metres, pixels of the disparity's resolution).

    - `cut_offset_m`: distance of the cut from the base along the axis (just outside the collar).
    - `erode_px`: mask erosion before reading depth (silhouette pixels mix branch and background).
    - `min_points`: fewest valid 3D points a branch needs; fewer → dropped.
    - `min_valid_fraction`: smallest share of eroded-mask pixels with valid depth; lower → dropped.
    - `min_confidence`: branches below are dropped rather than reported.
    - `disparity_noise_px`: expected disparity noise, sets the line fit's inlier band with depth.
    - `cut_tolerance_m`, `cut_disparity_noise_px`: the confidence includes the chance that the cut point's
      depth lies within `cut_tolerance_m` of the truth when its disparity is off by a Gaussian of σ =
      `cut_disparity_noise_px` (`depth_precision_score`; 0 = left out). Why: a depth error grows with Z²
      (Z = f·B/d), and without it a far cut point was as confident as a near one. Learned segmenter, SGBM,
      calibration and held-out scenes: of the cut points in the top quarter of confidence, 92–98 % were
      within 5 cm nearer than 1.5 m, 68–86 % at 2–3 m, 44–47 % beyond (`benchmarks/depth_precision.py`).
      0.15 px is the cut point's own disparity error there (its 3D error × f·B / Z² has a median of
      0.12–0.16 px between 1 and 3 m, where depth dominates it) and the value that ranks the calibration
      scenes' cut points best (area under the ROC curve 0.812 → 0.828 with the trunk band, 0.825 → 0.836
      with one look); a finer matcher's cut points want a lower one.
    - `min_inlier_band_m`: the inlier band's floor.
    - `min_range_m`, `max_range_m`: the working range; cut points outside it are dropped.
    - `surface_correction`: move the line from the visible surface onto the axis (cross-sections).
    - `max_instances`: most branch instances a frame may hold; more → `MaskError` (HTTP 422: a bad
      mask, refused before any geometry runs rather than holding the estimator for minutes).
    - `target_policy`: how `select_target` picks the target, one of `TARGET_POLICIES`;
      `target_min_confidence`: a branch below it is never the target. 0.7: with the default learned
      segmenter (network width 640, trunk band 40 px; its tables say 0.72 for one look, 0.7 at 1280) and
      SGBM, the lowest (calibrated) confidence, in hundredths, at and above which ≥ 90 % of cut points lie
      within 5 cm of a true one (its 240 calibration scenes in normal light; `benchmarks/segmenter.py`
      checks it held out: there 87 % of targets right at 640×360 (89 % at ≥ 0.8; 90 % from 0.83), 93 % in the
      roi mode at HD720; fitted on either half of the calibration scenes it reads 0.65 or 0.76). Out of normal
      light the learned segmenter may ask more (`BranchMasks.target_min_confidence`).
    - `max_cut_beyond_tip_m`: a branch whose visible part ends more than this short of its cut point (base +
      `cut_offset_m`) is dropped: that cut point lies in the air past the mask's end, a guess along the axis
      of a fragment (a stem seen between two leaves, a sliver along a board's edge). With the learned
      segmenter and SGBM such cut points were 5 % right (6 of 110 on calibration scenes 2861–2920); at
      0.01 m, false cut points a frame 6.45 → 5.03 there and 4.57 → 3.90 held out, recall −0.2 / −0.5
      points; truth masks lose none.
    - A branch whose base the image border cuts, or that something nearer hides at its base, is dropped
      (`branchrange.core.branch_base`: the true base lies beyond what is seen, so a cut point measured from
      the visible end is an artefact), and so is a cut point that projects outside the image.
      `base_occluder_gap_m`: how much nearer than the base (m) the pixels just past the base end must be
      to count as an occluder; more than a trunk's radius, as the trunk's front is that much nearer.
    - `tracking`: keep branch ids stable across frames (`branchrange.core.tracking`, tuned in
      `[branch_tracking]`; the daemon and replay want it, a single pair does not).
    """

    section = "cutpoints"
    error = CutPointConfigError
    limits = {
        "cut_offset_m": Limit.physical("cut_offset_m"),
        "erode_px": Limit(minimum=0, expected="≥ 0 px"),
        "min_points": Limit(minimum=3, expected="≥ 3 points"),
        "min_valid_fraction": Limit(minimum=0, maximum=1, expected="a fraction in [0, 1]"),
        "min_confidence": Limit(minimum=0, maximum=1, expected="a confidence in [0, 1]"),
        "disparity_noise_px": Limit(exclusive_minimum=0, expected="> 0 px"),
        "cut_tolerance_m": Limit(exclusive_minimum=0, maximum=1, expected="> 0 and ≤ 1 m"),
        "cut_disparity_noise_px": Limit(minimum=0, exclusive_maximum=10, expected="in [0, 10) px (0: left out)"),
        "min_inlier_band_m": Limit(exclusive_minimum=0, expected="> 0 m"),
        "min_range_m": Limit.physical("distance_m"),
        "max_range_m": Limit.physical("distance_m"),
        "max_instances": Limit(minimum=1, expected="≥ 1 instance"),
        "target_policy": Limit(enum=TARGET_POLICIES, expected="one of " + ", ".join(repr(p) for p in TARGET_POLICIES)),
        "target_min_confidence": Limit(minimum=0, maximum=1, expected="a confidence in [0, 1]"),
        "max_cut_beyond_tip_m": Limit(minimum=0, expected="≥ 0 m (a large value keeps every cut point)"),
        "base_occluder_gap_m": Limit(exclusive_minimum=0, expected="> 0 m (a large value turns the check off)"),
    }

    cut_offset_m: float = 0.05
    erode_px: int = 1
    min_points: int = 8
    min_valid_fraction: float = 0.15
    min_confidence: float = 0.0
    disparity_noise_px: float = 0.5
    cut_tolerance_m: float = 0.05
    cut_disparity_noise_px: float = 0.15
    min_inlier_band_m: float = 0.01
    min_range_m: float = 0.2
    max_range_m: float = 10.0
    surface_correction: bool = True
    max_instances: int = 256
    target_policy: str = DEFAULT_TARGET_POLICY
    target_min_confidence: float = 0.7
    tracking: bool = True
    max_cut_beyond_tip_m: float = 0.01
    base_occluder_gap_m: float = 0.1

    def checks(self) -> Checks:
        """The range of every setting; the working range within the physical distance range."""
        near_ok, distances = in_physical_range("distance_m", self.min_range_m)
        far_ok, _ = in_physical_range("distance_m", self.max_range_m)
        return {
            "cut_offset_m": in_physical_range("cut_offset_m", self.cut_offset_m),
            "min_range_m": (near_ok, distances),
            "max_range_m": (
                far_ok and self.max_range_m > self.min_range_m,
                f"> min_range_m ({self.min_range_m} m), {distances}",
            ),
        }


@dataclass
class BranchEstimate:
    """One branch's cut point. Vectors are `(3,)` metres in the rectified left camera frame.

    `id` is the stable track id (set by the tracker; the mask id until then), `mask_id` the
    instance id in the frame's mask, `pixel` the cut point's (u, v) in the left image, `axis` a
    unit vector from base toward tip. `working_scale`: its disparity came from the pair shrunk this many
    times (the roi mode's region budget): its fit took one pixel per working pixel and its disparity noise
    as that many full-resolution pixels.
    """

    mask_id: int
    cut_point_m: np.ndarray
    base_m: np.ndarray
    axis: np.ndarray
    distance_m: float
    pixel: tuple[float, float]
    diameter_m: float
    confidence: float
    valid_fraction: float
    residual_m: float
    n_points: int
    id: int = -1
    working_scale: int = 1


@dataclass(frozen=True)
class DroppedBranch:
    """A mask instance that gave no cut point, and why."""

    mask_id: int
    reason: str


@dataclass
class CutPointResult:
    """All cut points of a frame and the instances that were dropped."""

    branches: list[BranchEstimate] = field(default_factory=list)
    dropped: list[DroppedBranch] = field(default_factory=list)


def _surface_offset_factor(half_width_px: float, erode_px: int) -> float:
    """Mean depth of the visible front of a cylinder in units of its radius, after erosion.

    Visible points across the silhouette sit at `x = r·s`, depth `r·(1 − √(1 − s²))` nearer than the
    axis; erosion keeps `|s| ≤ a = 1 − e/w`. The mean of `√(1 − s²)` over `[−a, a]` is
    `(asin a + a√(1 − a²)) / (2a)` (π/4 when nothing is eroded).
    """
    if half_width_px <= 0:
        return math.pi / 4
    a = float(np.clip(1.0 - erode_px / half_width_px, 0.05, 1.0))
    return (math.asin(a) + a * math.sqrt(1.0 - a * a)) / (2.0 * a)


def _pixels_per_metre_across(point: np.ndarray, direction: np.ndarray, geometry: StereoGeometry) -> float:
    """Image width (px) of 1 m across a cylinder whose axis passes `point` (3,) along `direction`.

    The silhouette's edges lie on either side of the axis along `direction × point` (perpendicular
    to the axis and to the line of sight); their image separation is measured across the projected
    axis. Off the optical axis this is up to 1/cos θ more than f/Z — 20 % at 35°.
    """
    across = np.cross(direction, point)
    norm = vector_norm(across)
    eps = 1e-3 * max(float(point[2]), 1e-3)
    p0 = project(point, geometry)[0]
    along_px = project(point + eps * direction, geometry)[0] - p0
    if norm < 1e-9 or vector_norm(along_px) < 1e-9:  # axis along the line of sight
        return geometry.focal_px / float(point[2])
    across_px = (project(point + eps * across / norm, geometry)[0] - p0) / eps
    image_normal = np.array([-along_px[1], along_px[0]]) / vector_norm(along_px)
    return abs(float(across_px @ image_normal))


def _away_from_camera(point: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Unit vector (3,) perpendicular to `direction` pointing from the camera past `point`."""
    away = point - (point @ direction) * direction
    norm = vector_norm(away)
    return away / norm if norm > 1e-9 else np.zeros(3)


@dataclass(frozen=True)
class CylinderFit:
    """A branch or trunk as a cylinder: its axis (`Line3D`, m) and the evidence behind it.

    `silhouette` and `profile` are the image axis and width/centreline profile; `points` the 3D
    points of the valid pixels `pixels` (rows, cols) and `inliers` which of them the robust fit
    kept; `residual_m` the inliers' RMS misfit as depth (m) and `residual_ratio` the same
    relative to the inlier threshold (0 = perfect, 1 = at the threshold).
    """

    axis: Line3D
    silhouette: ImageAxis
    profile: WidthProfile
    valid_fraction: float
    points: np.ndarray
    pixels: tuple[np.ndarray, np.ndarray]
    inliers: np.ndarray
    residual_m: float
    residual_ratio: float

    @property
    def inlier_fraction(self) -> float:
        """Share of the valid points the fit kept."""
        return float(self.inliers.mean()) if self.inliers.size else 0.0

    def radius_at(self, point: np.ndarray, geometry: StereoGeometry, s: float | None = None) -> float:
        """Radius (m) at the axis point `point` (3,): local image width over the px-per-metre there.

        The width is read at the point's own image position, or at `s` (px along the silhouette).
        """
        if s is None:
            s = self.silhouette.coordinate(project(point, geometry)[0])
        s = float(np.clip(s, self.silhouette.s_lo, self.silhouette.s_hi))
        return radius_from_silhouette(
            self.profile.centre(self.silhouette, s),
            self.silhouette.normal,
            0.5 * self.profile.at(s),
            Line3D(np.asarray(point, dtype=np.float64), self.axis.direction),
            geometry,
        )


def _onto_axis(
    surface_point: np.ndarray,
    direction: np.ndarray,
    silhouette: ImageAxis,
    profile: WidthProfile,
    geometry: StereoGeometry,
    erode_px: int,
) -> np.ndarray:
    """A point of the visible-surface line moved back onto the cylinder axis (3,), metres.

    The surface points' mean depth lies `k·r` nearer than the axis (`_surface_offset_factor`), with
    `r` from the local width; two passes, as `r` depends on the depth it is measured at.
    """
    s = float(np.clip(silhouette.coordinate(project(surface_point, geometry)[0]), silhouette.s_lo, silhouette.s_hi))
    half_width_px = 0.5 * profile.at(s)
    k = _surface_offset_factor(half_width_px, erode_px)
    away = _away_from_camera(surface_point, direction)
    point = surface_point
    for _ in range(2):
        radius = half_width_px / _pixels_per_metre_across(point, direction, geometry)
        point = surface_point + k * radius * away
    return point


def _axis_in_disparity_space(
    s: np.ndarray,
    d: np.ndarray,
    silhouette: ImageAxis,
    profile: WidthProfile,
    geometry: StereoGeometry,
    threshold_px: float,
    min_points: int,
    margin_px: float | None,
) -> tuple[Line3D, LinearFit] | str:
    """A branch's line from disparity along the centreline (robust fit in px), lifted to 3D.

    Two stations at the 10th and 90th percentile of the inliers' positions. With `margin_px`
    None: centreline pixel + fitted disparity → the visible surface's line. Otherwise the axis
    itself: at each station the perspective-exact `cross_section` of the silhouette, whose
    fitted disparity is the mean over the pixels `margin_px` inside the edges; the direction it
    needs comes from the previous pass (three passes, starting from the surface line).
    """
    try:
        fit = fit_linear_robust(s, d, threshold_px, penalty_above=1.0)
    except GeometryError as exc:
        return f"no disparity line: {exc}"
    if fit.inliers.sum() < min_points:
        return f"disparity line fit kept {int(fit.inliers.sum())} points, fewer than {min_points}"
    stations = np.quantile(s[fit.inliers], [0.1, 0.9])
    disparities = fit.at(stations)
    if np.any(disparities <= 0):
        return "fitted disparity along the branch reaches zero (the branch would be at infinity)"
    centres = [profile.centre(silhouette, float(st)) for st in stations]
    ends = backproject(np.array([c[0] for c in centres]), np.array([c[1] for c in centres]), disparities, geometry)
    if margin_px is not None:
        rays = [
            section_rays(centre, silhouette.normal, 0.5 * profile.at(float(st)), margin_px, geometry)
            for centre, st in zip(centres, stations)
        ]
    for _ in range(0 if margin_px is None else 3):
        if vector_norm(ends[1] - ends[0]) < 1e-6:
            break
        ends = np.stack(
            [
                cross_section_from_rays(station, float(disparity), ends[1] - ends[0], geometry).axis_point_m
                for station, disparity in zip(rays, disparities)
            ]
        )
    if vector_norm(ends[1] - ends[0]) < 1e-6:
        return "branch too short to give an axis direction"
    return Line3D(ends[0], (ends[1] - ends[0]) / vector_norm(ends[1] - ends[0])), fit


def fit_cylinder(
    mask: np.ndarray | MaskCrop,
    disparity: np.ndarray,
    geometry: StereoGeometry,
    config: CutPointConfig,
    max_disparity: float | None = None,
    cut_by: np.ndarray | MaskCrop | None = None,
    stride: int = 1,
    max_points: int = 0,
) -> CylinderFit | str:
    """Fit a (possibly tapered) cylinder to one boolean `H×W` mask (or its `MaskCrop`: the work
    then follows the mask's size, not the image's) and the `H×W` disparity (px). `stride` > 1: the
    disparity was matched at that working scale (`region_budget`), so only one pixel per s×s block
    is a measurement: the fit takes those (`on_working_grid`), its cost bounded with the region's.
    `max_points` > 0: at most about that many pixels, every k-th of the mask's (the trunk near the tree).

    Elongated silhouettes: centreline from the mask, disparity along it by a robust linear fit
    (see `fit_linear_robust`); seen end-on: a robust 3D line through the points. Either line runs
    along the visible surface and is then pushed back onto the axis. Returns the fit, or the
    reason why the evidence does not support one.
    """
    crop = as_crop(mask)
    core = erode(crop.mask, config.erode_px)  # the crop's background margin erodes as the image would
    eroded_px = config.erode_px if np.count_nonzero(core) < np.count_nonzero(crop.mask) else 0
    rows, cols = crop.with_mask(core).pixels()
    if stride > 1:
        on_grid = on_working_grid(rows, cols, stride, config.min_points)
        rows, cols = rows[on_grid], cols[on_grid]
    if 0 < max_points < rows.size:
        every = -(-rows.size // max_points)
        rows, cols = rows[::every], cols[::every]
    if rows.size < config.min_points:
        return f"mask has {rows.size} pixels after erosion, fewer than {config.min_points}"
    d = disparity[rows, cols]
    valid = valid_disparity(d, max_disparity)
    valid_fraction = float(valid.mean())
    n_valid = int(valid.sum())
    if n_valid < config.min_points or valid_fraction < config.min_valid_fraction:
        return (
            f"only {n_valid} of {rows.size} mask pixels have valid depth "
            f"(need {config.min_points} and {config.min_valid_fraction:.0%})"
        )
    rows, cols, d = rows[valid].astype(np.float64), cols[valid].astype(np.float64), d[valid].astype(np.float64)
    points = backproject(cols, rows, d, geometry)
    silhouette = image_axis(crop, cut_by)
    profile = width_profile(silhouette)
    d_median = float(np.median(d))
    z_median = depth_from_disparity(d_median, geometry.focal_px, geometry.baseline_m)
    radius_guess = 0.5 * profile.at(0.0) * z_median / geometry.focal_px
    if silhouette.length_px >= 2.0 * max(1.0, profile.at(0.0)):
        # the visible front spans about d·r/Z px of disparity across the width
        threshold_px = 3.0 * config.disparity_noise_px + d_median * radius_guess / z_median
        s = (np.stack([cols, rows], axis=1) - silhouette.centre) @ silhouette.direction
        # erosion removes the pixels within erode_px (in u or v) of the edge: that far across it
        margin_px = eroded_px * float(np.max(np.abs(silhouette.normal)))
        lifted = _axis_in_disparity_space(
            s,
            d,
            silhouette,
            profile,
            geometry,
            threshold_px,
            config.min_points,
            margin_px if config.surface_correction else None,
        )
        if isinstance(lifted, str):
            return lifted
        line, disparity_fit = lifted
        inliers = disparity_fit.inliers
        residual_m = disparity_fit.residual * z_median**2 / geometry.fb
        residual_ratio = disparity_fit.residual / threshold_px
    else:
        depth_noise = z_median**2 / geometry.fb * config.disparity_noise_px
        # the visible surface strays up to ~1.3 r from the line through its centroid
        band_m = max(config.min_inlier_band_m, 3.0 * depth_noise, 1.5 * radius_guess)
        try:
            fit = fit_line_robust(points, band_m)
        except GeometryError as exc:
            return f"no 3D line: {exc}"
        if fit.inliers.sum() < config.min_points:
            return f"line fit kept {int(fit.inliers.sum())} points, fewer than {config.min_points}"
        line, inliers, residual_m, residual_ratio = fit.line, fit.inliers, fit.residual_m, fit.residual_m / band_m
        if config.surface_correction:
            t = line.parameters(points[inliers])
            t_lo, t_hi = np.quantile(t, [0.1, 0.9])
            a = _onto_axis(line.at(t_lo), line.direction, silhouette, profile, geometry, eroded_px)
            b = _onto_axis(line.at(t_hi), line.direction, silhouette, profile, geometry, eroded_px)
            line = Line3D(a, (b - a) / vector_norm(b - a)) if vector_norm(b - a) > 1e-3 else Line3D(a, line.direction)
    return CylinderFit(
        line,
        silhouette,
        profile,
        valid_fraction,
        points,
        (rows.astype(np.int64), cols.astype(np.int64)),
        inliers,
        float(residual_m),
        float(min(1.0, residual_ratio)),
    )


@dataclass(frozen=True)
class TrunkModel:
    """The trunk as a tapered cylinder fitted from its mask (see `fit_cylinder`)."""

    cylinder: CylinderFit
    geometry: StereoGeometry

    def surface_distance(self, point: np.ndarray) -> float:
        """Distance (m) of `point` (3,) from the trunk's surface (0 on the bark, < 0 inside)."""
        axis = self.cylinder.axis
        foot = axis.at(axis.parameters(point[None])[0])
        return vector_norm(point - foot) - self.cylinder.radius_at(foot, self.geometry)

    def exit_point(self, branch_axis: Line3D, toward_tip: np.ndarray) -> np.ndarray | None:
        """Where the branch axis leaves the trunk surface on its way to the tip (3,), metres.

        Solves |offset of axis(t) from the trunk axis| = radius for t (a quadratic) and keeps the
        crossing furthest along `toward_tip` (the axis also crosses the trunk's far side); the
        radius is the trunk's local one at the crossing (two passes). None when the branch axis
        misses the trunk.
        """
        trunk_axis = self.cylinder.axis
        a = trunk_axis.direction
        d_perp = branch_axis.direction - (branch_axis.direction @ a) * a
        w = branch_axis.point - trunk_axis.point
        w_perp = w - (w @ a) * a
        qa, qb = d_perp @ d_perp, d_perp @ w_perp
        if qa < 1e-9:
            return None
        sign = 1.0 if branch_axis.direction @ toward_tip >= 0 else -1.0
        t_closest = -qb / qa
        radius = self.cylinder.radius_at(
            trunk_axis.at(trunk_axis.parameters(branch_axis.at(t_closest)[None])[0]), self.geometry
        )
        crossing = None
        for _ in range(2):
            disc = qb * qb - qa * (w_perp @ w_perp - radius**2)
            if disc < 0:
                return None
            t = (-qb + sign * math.sqrt(disc)) / qa
            crossing = branch_axis.at(t)
            foot = trunk_axis.at(trunk_axis.parameters(crossing[None])[0])
            radius = self.cylinder.radius_at(foot, self.geometry)
        return crossing


def fit_trunk(
    trunk: np.ndarray | MaskCrop,
    disparity: np.ndarray,
    geometry: StereoGeometry,
    config: CutPointConfig,
    max_disparity: float | None = None,
    max_points: int = 0,
) -> TrunkModel | None:
    """A `TrunkModel` from the boolean `H×W` trunk mask (or its `MaskCrop`) and the disparity (px); None when the
    trunk's depth is too thin to fit or it is not elongated (no axis to speak of). `max_points` > 0: fitted on
    about that many of its pixels at most (`fit_cylinder`)."""
    try:
        cylinder = fit_cylinder(trunk, disparity, geometry, config, max_disparity, max_points=max_points)
    except GeometryError:
        return None
    if isinstance(cylinder, str):
        return None
    if cylinder.silhouette.length_px < 1.5 * cylinder.profile.at(0.0):
        return None
    return TrunkModel(cylinder, geometry)


def _confidence(
    cylinder: CylinderFit, stereo_conf: float, depth_m: float, geometry: StereoGeometry, config: CutPointConfig
) -> float:
    """Product of five scores in [0, 1] — all must be good for a confident cut point:
    valid-depth share (full at ≥ 0.8), fit (inlier share × (1 − ½·residual/band)), mean stereo
    confidence of the points, amount of evidence (full at 4× `min_points` inliers) and the depth's
    precision at the cut point's depth `depth_m` (`depth_precision_score`)."""
    valid_score = min(1.0, cylinder.valid_fraction / 0.8)
    fit_score = cylinder.inlier_fraction * (1.0 - 0.5 * cylinder.residual_ratio)
    evidence_score = min(1.0, int(cylinder.inliers.sum()) / (4.0 * config.min_points))
    precision_score = depth_precision_score(depth_m, geometry, config)
    return float(np.clip(valid_score * fit_score * stereo_conf * evidence_score * precision_score, 0.0, 1.0))


def depth_precision_score(depth_m: float, geometry: StereoGeometry, config: CutPointConfig) -> float:
    """The chance in [0, 1] that a cut point at depth `depth_m` (m) has its depth within `cut_tolerance_m`:
    erf(tolerance / (√2·σ_Z)), σ_Z = Z²·σ_d / (f·B) the depth error of a disparity error σ_d =
    `cut_disparity_noise_px` (first order in Z = f·B / d); 1 when σ_d is 0."""
    if config.cut_disparity_noise_px == 0:
        return 1.0
    sigma_z = depth_m**2 * config.cut_disparity_noise_px / geometry.fb
    return math.erf(config.cut_tolerance_m / (math.sqrt(2.0) * sigma_z))


def _trunk_side_in_image(silhouette: ImageAxis, trunk: MaskCrop, slice_px: float) -> bool | None:
    """Whether the low end of the silhouette is the one nearer the trunk mask in the image; None
    when both ends are about equally near (a branch lying across the trunk's silhouette)."""
    u, v = np.array([silhouette.end_centre(low, slice_px) for low in (True, False)]).T
    ends = trunk.distances_at(np.array([round(x) for x in v]), np.array([round(x) for x in u]))
    if abs(ends[0] - ends[1]) <= 0.1 * silhouette.length_px:
        return None
    return bool(ends[0] < ends[1])


def _low_end_is_base(
    cylinder: CylinderFit,
    ends: tuple[np.ndarray, np.ndarray],
    geometry: StereoGeometry,
    trunk: MaskCrop | None,
    trunk_model: TrunkModel | None,
    slice_px: float,
) -> bool:
    """Which of the two lifted silhouette ends (low, high) is the base, in order of evidence:
    1. the end nearer the trunk's surface in 3D (when the trunk was fitted and one end is clearly
       nearer: 5 cm, or half the other's distance);
    2. the end nearer the trunk's mask in the image;
    3. the thicker end in metres (not in pixels: a tip pointing at the camera looks thick).
    """
    if trunk_model is not None:
        gaps = [trunk_model.surface_distance(end) for end in ends]
        if abs(gaps[0] - gaps[1]) > max(0.05, 0.5 * max(gaps)):
            return bool(gaps[0] < gaps[1])
    if trunk is not None:
        side = _trunk_side_in_image(cylinder.silhouette, trunk, slice_px)
        if side is not None:
            return side
    silhouette = cylinder.silhouette
    radius_low = cylinder.radius_at(ends[0], geometry, silhouette.s_lo + slice_px / 2)
    radius_high = cylinder.radius_at(ends[1], geometry, silhouette.s_hi - slice_px / 2)
    return bool(radius_low >= radius_high)


@dataclass(frozen=True)
class BranchEnds:
    """A branch's `base` and `tip` on its axis (3,) metres; `base_at_low`: whether the base is the
    silhouette's low end (None seen end-on); `base_on_trunk`: the base is where the axis leaves the
    fitted trunk's bark (placed by the trunk's geometry, not by where the silhouette stops)."""

    base: np.ndarray
    tip: np.ndarray
    base_at_low: bool | None
    base_on_trunk: bool


def _ends(
    cylinder: CylinderFit, geometry: StereoGeometry, trunk: MaskCrop | None, trunk_model: TrunkModel | None
) -> BranchEnds:
    """Base and tip of a branch on its axis.

    Elongated silhouettes: the mask's ends lifted onto the axis; at a fitted trunk the base is
    where the axis leaves the bark (the mask's end there is where the branch vanishes into the
    trunk's silhouette, far from the bark when the branch points at or away from the camera).
    A silhouette seen end-on has no ends: the inlier points' extent, the deeper end as the base.
    """
    line, silhouette = cylinder.axis, cylinder.silhouette
    if silhouette.length_px < 2.0 * max(1.0, cylinder.profile.at(0.0)):
        t = line.parameters(cylinder.points[cylinder.inliers])
        ends = line.at(np.quantile(t, [0.02, 0.98]))
        base, tip = (ends[0], ends[1]) if ends[0][2] >= ends[1][2] else (ends[1], ends[0])
        return BranchEnds(base, tip, None, False)
    slice_px = max(3.0, 0.15 * silhouette.length_px)
    ends_px = [silhouette.end_centre(at_low, slice_px) for at_low in (True, False)]
    low, high = (line.closest_to_ray(pixel_ray(u, v, geometry)) for u, v in ends_px)
    base_at_low = _low_end_is_base(cylinder, (low, high), geometry, trunk, trunk_model, slice_px)
    base, tip = (low, high) if base_at_low else (high, low)
    if trunk_model is not None:
        exit_m = trunk_model.exit_point(line, tip - base)
        if exit_m is not None and vector_norm(exit_m - base) < 0.5 * vector_norm(tip - base) + 0.1:
            return BranchEnds(exit_m, tip, base_at_low, True)
    return BranchEnds(base, tip, base_at_low, False)


def _base_out_of_view(
    mask: MaskCrop,
    cylinder: CylinderFit,
    ends: BranchEnds,
    disparity: np.ndarray,
    geometry: StereoGeometry,
    config: CutPointConfig,
    trunk: MaskCrop | None,
    max_disparity: float | None,
) -> str | None:
    """Why the branch's base is not seen (`branchrange.core.branch_base`), or None when it is.

    A base placed on a fitted trunk is measured, not read off the silhouette's end, so only the
    silhouette's own ends are checked — but it must itself be in the image: a trunk's cylinder carried
    beyond the frame is an extrapolation (flown at 640×360, such bases put cut points at the bottom edge
    5–8 cm off).
    """
    if ends.base_on_trunk:
        u, v = project(ends.base, geometry)[0]
        height, width = disparity.shape
        if not (0.0 <= u <= width - 1 and 0.0 <= v <= height - 1):
            return "the branch meets the trunk outside the image: its cut point is not in view"
        return None
    if base_cut_by_image_border(mask, cylinder.silhouette, ends.base_at_low):
        return "the image border cuts the branch at its base: the cut point lies outside the view"
    if ends.base_at_low is not None and base_hidden_by_occluder(
        mask,
        cylinder.silhouette,
        ends.base_at_low,
        ends.base,
        disparity,
        geometry,
        min_gap_m=config.base_occluder_gap_m,
        trunk=trunk,
        max_disparity=max_disparity,
    ):
        return "something nearer hides the branch at its base: the cut point is not in view"
    return None


def estimate_branch(
    mask_id: int,
    mask: np.ndarray | MaskCrop,
    disparity: np.ndarray,
    geometry: StereoGeometry,
    config: CutPointConfig,
    *,
    confidence: np.ndarray | None = None,
    trunk: np.ndarray | MaskCrop | None = None,
    trunk_model: TrunkModel | None = None,
    max_disparity: float | None = None,
    reported_confidence: Callable[[float, float], float] | None = None,
    working_scale: int = 1,
) -> BranchEstimate | DroppedBranch:
    """Cut point of one branch from its boolean `H×W` mask (or `MaskCrop`) and the `H×W` disparity (px).

    `confidence` (`H×W` in [0, 1]) is the stereo backend's per-pixel confidence (1 when None),
    `trunk` the boolean trunk mask when known and `trunk_model` its fitted cylinder (the base is
    then where the axis pierces the bark). `reported_confidence` maps the cut point's own confidence
    and the branch's visible length (m, base to tip) to the reported one (`BranchMasks.reported_confidence`:
    the segmenter's belief in the instance, how long it is seen, and its calibration; None = as it is).
    `working_scale` > 1: its disparity was matched at that scale (`region_budget`): the fit takes one pixel
    per working pixel, and the disparity noise settings (`disparity_noise_px`, `cut_disparity_noise_px`)
    count working pixels — that many full-resolution ones — so its inlier band and confidence say so.
    Returns a `DroppedBranch` with the reason when the evidence does not support a cut point.
    """
    try:
        return _estimate_branch(
            mask_id,
            as_crop(mask),
            disparity,
            geometry,
            config,
            confidence,
            None if trunk is None else as_crop(trunk),
            trunk_model,
            max_disparity,
            reported_confidence,
            working_scale,
        )
    except GeometryError as exc:  # e.g. the axis runs behind the camera: the depth is inconsistent
        return DroppedBranch(mask_id, f"no consistent branch axis: {exc}")


def _estimate_branch(
    mask_id: int,
    mask: MaskCrop,
    disparity: np.ndarray,
    geometry: StereoGeometry,
    config: CutPointConfig,
    confidence: np.ndarray | None,
    trunk: MaskCrop | None,
    trunk_model: TrunkModel | None,
    max_disparity: float | None,
    reported_confidence: Callable[[float, float], float] | None = None,
    working_scale: int = 1,
) -> BranchEstimate | DroppedBranch:
    """`estimate_branch` without the guard against degenerate geometry."""
    if working_scale > 1:
        config = replace(
            config,
            disparity_noise_px=config.disparity_noise_px * working_scale,
            cut_disparity_noise_px=config.cut_disparity_noise_px * working_scale,
        )
    cylinder = fit_cylinder(mask, disparity, geometry, config, max_disparity, cut_by=trunk, stride=working_scale)
    if isinstance(cylinder, str):
        return DroppedBranch(mask_id, cylinder)
    ends = _ends(cylinder, geometry, trunk, trunk_model)
    hidden = _base_out_of_view(mask, cylinder, ends, disparity, geometry, config, trunk, max_disparity)
    if hidden is not None:
        return DroppedBranch(mask_id, hidden)
    base_m, tip_m = ends.base, ends.tip
    line = cylinder.axis
    axis = line.direction if line.direction @ (tip_m - base_m) >= 0 else -line.direction
    visible_m = vector_norm(tip_m - base_m)
    if config.cut_offset_m > visible_m + config.max_cut_beyond_tip_m:
        return DroppedBranch(
            mask_id,
            f"the cut point ({100 * config.cut_offset_m:.0f} cm from the base) lies beyond the visible branch "
            f"({100 * visible_m:.1f} cm long)",
        )
    cut_m = base_m + config.cut_offset_m * axis
    distance = vector_norm(cut_m)
    if not config.min_range_m <= distance <= config.max_range_m:
        return DroppedBranch(
            mask_id,
            f"cut point at {distance:.2f} m is outside the working range {config.min_range_m}–{config.max_range_m} m",
        )
    if cut_m[2] <= 0:
        return DroppedBranch(mask_id, "cut point lies behind the camera")
    pixel = project(cut_m, geometry)[0]
    height, width = disparity.shape
    if not (0.0 <= pixel[0] <= width - 1 and 0.0 <= pixel[1] <= height - 1):
        return DroppedBranch(
            mask_id,
            f"the cut point projects to ({pixel[0]:.0f}, {pixel[1]:.0f}) px, outside the {width}×{height} image",
        )
    diameter = 2.0 * cylinder.radius_at(cut_m, geometry)
    rows, cols = cylinder.pixels
    inliers = cylinder.inliers
    stereo_conf = float(np.mean(confidence[rows, cols][inliers])) if confidence is not None else 1.0
    score = _confidence(cylinder, stereo_conf if np.isfinite(stereo_conf) else 0.0, float(cut_m[2]), geometry, config)
    if reported_confidence is not None:
        score = reported_confidence(score, visible_m)
    if score < config.min_confidence:
        return DroppedBranch(mask_id, f"confidence {score:.2f} below {config.min_confidence}")
    return BranchEstimate(
        mask_id=mask_id,
        cut_point_m=cut_m,
        base_m=base_m,
        axis=axis,
        distance_m=distance,
        pixel=(float(pixel[0]), float(pixel[1])),
        diameter_m=float(diameter),
        confidence=score,
        valid_fraction=cylinder.valid_fraction,
        residual_m=cylinder.residual_m,
        n_points=int(inliers.sum()),
        id=mask_id,
        working_scale=working_scale,
    )


def estimate_cut_points(
    masks: BranchMasks,
    disparity: np.ndarray,
    geometry: StereoGeometry,
    config: CutPointConfig = CutPointConfig(),
    *,
    confidence: np.ndarray | None = None,
    max_disparity: float | None = None,
    trunk_model: TrunkModel | None | Literal["fit"] = "fit",
    working_scales: Mapping[int, int] | None = None,
) -> CutPointResult:
    """Cut points of every branch instance in `masks` from the `H×W` disparity (px).

    `trunk_model`: "fit" fits the trunk's cylinder from its mask here; a `TrunkModel` fitted
    elsewhere (the roi mode fits it on the coarse pass, in metres like any other) or None is used
    as it is. `working_scales`: mask id → the scale its disparity was matched at (`region_budget.branch_scales`;
    absent: full resolution), see `estimate_branch`.

    Shapes must agree (the caller validates); `confidence` is the stereo confidence `H×W` in [0, 1].
    Each instance is read from its bounding box (`BranchMasks.crop`), so the cost follows the
    branches' pixels, not the frame's: a full-resolution disparity that is empty outside a few
    regions costs what the regions cost. More than `config.max_instances` branch instances raise
    `MaskError` (a ValueError) before any geometry runs.
    """
    disparity = np.asarray(disparity, dtype=np.float32)
    if disparity.shape != masks.shape:
        raise ValueError(f"disparity is {disparity.shape} but the mask is {masks.shape} (H, W)")
    check_instance_count(masks, config.max_instances)
    trunk = masks.trunk_crop()
    if trunk_model == "fit":
        trunk_model = None if trunk is None else fit_trunk(trunk, disparity, geometry, config, max_disparity)
    result = CutPointResult()
    for mask_id in masks.branch_ids():
        crop = masks.crop(mask_id)
        assert crop is not None, "every id of branch_ids() has pixels, hence a crop"
        outcome = estimate_branch(
            mask_id,
            crop,
            disparity,
            geometry,
            config,
            confidence=confidence,
            trunk=trunk,
            trunk_model=trunk_model,
            max_disparity=max_disparity,
            reported_confidence=masks.reported_confidence(mask_id),
            working_scale=(working_scales or {}).get(mask_id, 1),
        )
        if isinstance(outcome, DroppedBranch):
            result.dropped.append(outcome)
        else:
            result.branches.append(outcome)
    return result


def target_score(policy: TargetPolicy | str, distance_m: float, confidence: float, diameter_m: float) -> float:
    """How good a target a cut point is under `policy`: lower is better (see `select_target`).

    One ranking for the per-frame target and the fused world tracks (`mavlink.world_tracks`), so both
    pick by the same rule; `confidence` must be > 0 for `nearest_confident`.
    """
    if policy == "nearest_confident":
        return distance_m / confidence
    if policy == "nearest":
        return distance_m
    if policy == "most_confident":
        return -confidence
    if policy == "thickest":
        return -diameter_m
    raise CutPointConfigError(f"target policy {policy!r} is not one of {', '.join(TARGET_POLICIES)}")


def select_target(
    branches: list[BranchEstimate],
    policy: TargetPolicy = DEFAULT_TARGET_POLICY,
    min_confidence: float = 0.3,
) -> BranchEstimate | None:
    """The branch a controller should approach, or None when no branch is confident enough.

    `nearest_confident` (default): smallest distance / confidence — the nearest branch, a less
    certain one counting as farther (at 0.5 confidence, twice as far); `nearest`: smallest
    distance; `most_confident`: highest confidence; `thickest`: largest diameter. Only branches
    with confidence ≥ `min_confidence` (and > 0) take part.
    Why not plain `nearest` by default: with stereo noise a cut point estimated too near wins it
    by its error, and confidence tracks the error (sgbm, ground-truth masks, 50 synthetic
    scenes: 87 % of cut points at confidence ≥ 0.9 lie within 5 cm, 38 % at 0.3–0.5).
    """
    if policy not in TARGET_POLICIES:
        raise CutPointConfigError(f"target policy {policy!r} is not one of {', '.join(TARGET_POLICIES)}")
    candidates = [b for b in branches if b.confidence >= min_confidence and b.confidence > 0]
    if not candidates:
        return None
    return min(candidates, key=lambda b: target_score(policy, b.distance_m, b.confidence, b.diameter_m))
