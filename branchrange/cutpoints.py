"""Cut points of branches: from a disparity map and branch masks to where the pruning tool must go.

Per branch (design.md, Cut points):
1. 3D points from valid disparity inside the slightly eroded mask.
2. A robust 3D line fit (RANSAC + IRLS) gives the axis. Stereo sees the branch's front surface,
   which lies about π/4·r nearer than the axis on average, so the fitted line is pushed back by
   that amount (`surface_correction`).
3. The ends come from the mask in the image (exact where depth is not: near the trunk, depth is
   often occluded), lifted onto the 3D axis. The base is the end meeting the trunk when a trunk is
   known, else the thicker end (for a branch seen end-on, the deeper end).
4. Cut point = base + `cut_offset_m` along the axis toward the tip; distance from the camera;
   diameter = image width across the axis × Z / f; confidence ∈ [0, 1] from the valid-depth
   fraction, the fit (inlier share and residual), the stereo confidence and the amount of evidence.
A branch with too little evidence is dropped with a reason, never invented.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np

from branchrange.geometry import (
    GeometryError,
    Line3D,
    LineFit,
    StereoGeometry,
    backproject,
    fit_line_robust,
    pixel_ray,
    project,
    valid_disparity,
)
from branchrange.masks import BranchMasks, erode

TargetPolicy = Literal["nearest", "most_confident", "thickest"]
TARGET_POLICIES: tuple[str, ...] = ("nearest", "most_confident", "thickest")


class CutPointConfigError(ValueError):
    """A cut-point setting out of its range; the message names the key."""


@dataclass(frozen=True)
class CutPointConfig:
    """Settings of the cut-point stage (lengths in metres, pixels of the disparity's resolution).

    - `cut_offset_m`: distance of the cut from the base along the axis (just outside the collar).
    - `erode_px`: mask erosion before reading depth (silhouette pixels mix branch and background).
    - `min_points`: fewest valid 3D points a branch needs; fewer → dropped.
    - `min_valid_fraction`: smallest share of eroded-mask pixels with valid depth; lower → dropped.
    - `min_confidence`: branches below are dropped rather than reported.
    - `disparity_noise_px`: expected disparity noise, sets the line fit's inlier band with depth.
    - `min_inlier_band_m`: the inlier band's floor.
    - `min_range_m`, `max_range_m`: the working range; cut points outside it are dropped.
    - `surface_correction`: push the axis back from the visible surface by the expected amount.
    """

    cut_offset_m: float = 0.05
    erode_px: int = 1
    min_points: int = 30
    min_valid_fraction: float = 0.15
    min_confidence: float = 0.0
    disparity_noise_px: float = 0.5
    min_inlier_band_m: float = 0.01
    min_range_m: float = 0.2
    max_range_m: float = 10.0
    surface_correction: bool = True

    def __post_init__(self) -> None:
        checks = {
            "cut_offset_m": self.cut_offset_m >= 0,
            "erode_px": self.erode_px >= 0,
            "min_points": self.min_points >= 3,
            "min_valid_fraction": 0 <= self.min_valid_fraction <= 1,
            "min_confidence": 0 <= self.min_confidence <= 1,
            "disparity_noise_px": self.disparity_noise_px > 0,
            "min_inlier_band_m": self.min_inlier_band_m > 0,
            "min_range_m": self.min_range_m >= 0,
            "max_range_m": self.max_range_m > self.min_range_m,
        }
        for key, ok in checks.items():
            if not ok:
                raise CutPointConfigError(f"cutpoints.{key} = {getattr(self, key)!r} is out of range")


@dataclass
class BranchEstimate:
    """One branch's cut point. Vectors are `(3,)` metres in the rectified left camera frame.

    `id` is the stable track id (set by the tracker; the mask id until then), `mask_id` the
    instance id in the frame's mask, `pixel` the cut point's (u, v) in the left image, `axis` a
    unit vector from base toward tip.
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

    def to_dict(self) -> dict:
        """The branch entry of a `branchrange/v1` result."""
        return {
            "id": int(self.id),
            "mask_id": int(self.mask_id),
            "cut_point_m": [round(float(v), 5) for v in self.cut_point_m],
            "distance_m": round(float(self.distance_m), 5),
            "pixel": [round(float(self.pixel[0]), 2), round(float(self.pixel[1]), 2)],
            "diameter_m": round(float(self.diameter_m), 5),
            "axis": [round(float(v), 5) for v in self.axis],
            "base_m": [round(float(v), 5) for v in self.base_m],
            "confidence": round(float(self.confidence), 4),
            "valid_fraction": round(float(self.valid_fraction), 4),
            "residual_m": round(float(self.residual_m), 5),
            "points": int(self.n_points),
        }


@dataclass(frozen=True)
class DroppedBranch:
    """A mask instance that gave no cut point, and why."""

    mask_id: int
    reason: str

    def to_dict(self) -> dict:
        """The `dropped` entry of a `branchrange/v1` result."""
        return {"mask_id": int(self.mask_id), "reason": self.reason}


@dataclass
class CutPointResult:
    """All cut points of a frame and the instances that were dropped."""

    branches: list[BranchEstimate] = field(default_factory=list)
    dropped: list[DroppedBranch] = field(default_factory=list)


@dataclass(frozen=True)
class _ImageAxis:
    """The branch's silhouette in the image: centroid, unit axis and perpendicular (px), pixel
    coordinates along (`s`) and across (`n`) the axis, and its extent `s_lo..s_hi`."""

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

    def width_near(self, s: float, half_window_px: float) -> float:
        """Silhouette width in px around position `s`: pixel count per unit length in the window.

        Counting pixels per unit length measures width without raster artefacts at any angle.
        """
        lo, hi = max(s - half_window_px, self.s_lo), min(s + half_window_px, self.s_hi)
        if hi - lo < 1.0:
            lo, hi = s - 0.5, s + 0.5
        count = np.count_nonzero((self.s >= lo) & (self.s < hi))
        return count / (hi - lo)


def _median_width(axis: "_ImageAxis", slice_px: float = 2.0) -> float:
    """Median silhouette width (px) over slices across the axis: robust to a few slices that are
    occluded (a branch crossing the trunk) or widened (a stub)."""
    bins = np.floor((axis.s - axis.s_lo) / slice_px).astype(np.int64)
    counts = np.bincount(bins[bins >= 0])
    counts = counts[: max(1, int(axis.length_px // slice_px))]
    return float(np.median(counts)) / slice_px


def _image_axis(mask: np.ndarray) -> _ImageAxis:
    """Principal axis of a boolean `H×W` mask's pixels; extent from the 0.2/99.8 % quantiles."""
    v, u = np.nonzero(mask)
    pixels = np.stack([u, v], axis=1).astype(np.float64)
    centre = pixels.mean(axis=0)
    centred = pixels - centre
    _, vectors = np.linalg.eigh(centred.T @ centred)
    direction = vectors[:, -1]
    normal = np.array([-direction[1], direction[0]])
    s, n = centred @ direction, centred @ normal
    s_lo, s_hi = np.quantile(s, [0.002, 0.998])
    return _ImageAxis(centre, direction, normal, s, n, float(s_lo) - 0.5, float(s_hi) + 0.5)


def _end_centre(axis: _ImageAxis, at_low_end: bool, depth_px: float) -> np.ndarray:
    """Pixel on the silhouette's centreline at one end (centre across the axis of the end slice)."""
    s_end = axis.s_lo if at_low_end else axis.s_hi
    in_slice = (axis.s <= axis.s_lo + depth_px) if at_low_end else (axis.s >= axis.s_hi - depth_px)
    n_mid = float(np.median(axis.n[in_slice])) if np.any(in_slice) else 0.0
    return axis.point(s_end, n_mid)


def _base_is_low_end(axis: _ImageAxis, trunk: np.ndarray | None) -> tuple[bool, bool]:
    """Which silhouette end is the base — nearer the trunk when one is known, else the thicker
    one — and whether the trunk decided it."""
    slice_px = max(3.0, 0.15 * axis.length_px)
    if trunk is not None:
        distance_to_trunk = cv2.distanceTransform((~trunk).astype(np.uint8), cv2.DIST_L2, 5)
        h, w = trunk.shape
        ends = []
        for low in (True, False):
            u, v = _end_centre(axis, low, slice_px)
            ends.append(distance_to_trunk[int(np.clip(round(v), 0, h - 1)), int(np.clip(round(u), 0, w - 1))])
        if abs(ends[0] - ends[1]) > 0.1 * axis.length_px:
            return bool(ends[0] < ends[1]), True
    width_low = axis.width_near(axis.s_lo + slice_px / 2, slice_px / 2)
    width_high = axis.width_near(axis.s_hi - slice_px / 2, slice_px / 2)
    return bool(width_low >= width_high), False


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


def _radius_from_width(half_width_px: float, surface_depth_m: float, focal_px: float, erode_px: int) -> float:
    """Cylinder radius (m) from its silhouette half-width (px) and the median depth of its visible
    front (m): the axis lies `k·r` behind that front, so `r = w·(Z + k·r)/f`, i.e.
    `r = w·Z / (f − w·k)` with `k` from `_surface_offset_factor`."""
    k = _surface_offset_factor(half_width_px, erode_px)
    return half_width_px * surface_depth_m / max(focal_px - half_width_px * k, 1e-6 * focal_px)


def _pushed_back(line: Line3D, amount_m: float) -> Line3D:
    """The line moved `amount_m` away from the camera, perpendicular to itself (toward the axis)."""
    away = line.point / np.linalg.norm(line.point)
    away = away - (away @ line.direction) * line.direction
    norm = np.linalg.norm(away)
    if norm < 1e-6:  # line through the camera: no perpendicular direction away from it
        return line
    return Line3D(line.point + amount_m * away / norm, line.direction)


@dataclass(frozen=True)
class TrunkModel:
    """The trunk as a cylinder: its axis (a `Line3D`, metres) and radius (m), fitted from its mask."""

    axis: Line3D
    radius_m: float

    def exit_point(self, branch_axis: Line3D, toward_tip: np.ndarray) -> np.ndarray | None:
        """Where the branch axis leaves the trunk surface on its way to the tip (3,), metres.

        Solves |offset of axis(t) from the trunk axis| = radius for t (a quadratic) and keeps the
        crossing furthest along `toward_tip` (the axis also crosses the trunk's far side); None
        when the branch axis misses the trunk cylinder.
        """
        a = self.axis.direction
        d_perp = branch_axis.direction - (branch_axis.direction @ a) * a
        w = branch_axis.point - self.axis.point
        w_perp = w - (w @ a) * a
        qa, qb, qc = d_perp @ d_perp, d_perp @ w_perp, w_perp @ w_perp - self.radius_m ** 2
        disc = qb * qb - qa * qc
        if qa < 1e-9 or disc < 0:
            return None
        roots = (-qb + np.array([-1.0, 1.0]) * math.sqrt(disc)) / qa
        sign = 1.0 if branch_axis.direction @ toward_tip >= 0 else -1.0
        return branch_axis.at(roots[np.argmax(sign * roots)])


def fit_trunk(trunk: np.ndarray, disparity: np.ndarray, geometry: StereoGeometry, config: CutPointConfig,
              max_disparity: float | None = None) -> TrunkModel | None:
    """A `TrunkModel` from the boolean `H×W` trunk mask and the disparity (px); None when the
    trunk's depth is too thin to fit or it is not elongated (no axis to speak of)."""
    core = erode(trunk, config.erode_px)
    rows, cols = np.nonzero(core)
    d = disparity[rows, cols]
    valid = valid_disparity(d, max_disparity)
    if valid.sum() < config.min_points:
        return None
    points = backproject(cols[valid], rows[valid], d[valid], geometry)
    axis2d = _image_axis(trunk)
    half_width_px = _median_width(axis2d) / 2
    if axis2d.length_px < 3.0 * half_width_px:
        return None
    z_median = float(np.median(points[:, 2]))
    radius_m = _radius_from_width(half_width_px, z_median, geometry.focal_px, config.erode_px)
    band_m = max(config.min_inlier_band_m, 3.0 * z_median ** 2 / geometry.fb * config.disparity_noise_px, radius_m)
    try:
        fit = fit_line_robust(points, band_m)
    except GeometryError:
        return None
    line = fit.line
    if config.surface_correction:
        line = _pushed_back(line, radius_m * _surface_offset_factor(half_width_px, config.erode_px))
    return TrunkModel(line, radius_m)


def _confidence(valid_fraction: float, fit: LineFit, band_m: float, stereo_conf: float, n_inliers: int,
                config: CutPointConfig) -> float:
    """Product of four scores in [0, 1] — all must be good for a confident cut point:
    valid-depth share (full at ≥ 0.8), fit (inlier share × (1 − ½·residual/band)), mean stereo
    confidence of the points, and amount of evidence (full at 4× `min_points` inliers)."""
    valid_score = min(1.0, valid_fraction / 0.8)
    fit_score = fit.inlier_fraction * (1.0 - 0.5 * min(1.0, fit.residual_m / band_m))
    evidence_score = min(1.0, n_inliers / (4.0 * config.min_points))
    return float(np.clip(valid_score * fit_score * stereo_conf * evidence_score, 0.0, 1.0))


def estimate_branch(
    mask_id: int,
    mask: np.ndarray,
    disparity: np.ndarray,
    geometry: StereoGeometry,
    config: CutPointConfig,
    *,
    confidence: np.ndarray | None = None,
    trunk: np.ndarray | None = None,
    trunk_model: TrunkModel | None = None,
    max_disparity: float | None = None,
) -> BranchEstimate | DroppedBranch:
    """Cut point of one branch from its boolean `H×W` mask and the `H×W` disparity (px).

    `confidence` (`H×W` in [0, 1]) is the stereo backend's per-pixel confidence (1 when None),
    `trunk` the boolean trunk mask when known and `trunk_model` its fitted cylinder (the base is
    then where the axis pierces the bark). Returns a `DroppedBranch` with the reason when the
    evidence does not support a cut point.
    """
    core = erode(mask, config.erode_px)
    rows, cols = np.nonzero(core)
    if rows.size < config.min_points:
        return DroppedBranch(mask_id, f"mask has {rows.size} pixels after erosion, fewer than {config.min_points}")
    d = disparity[rows, cols]
    valid = valid_disparity(d, max_disparity)
    valid_fraction = float(valid.mean())
    n_valid = int(valid.sum())
    if n_valid < config.min_points or valid_fraction < config.min_valid_fraction:
        return DroppedBranch(mask_id, f"only {n_valid} of {rows.size} mask pixels have valid depth "
                                      f"(need {config.min_points} and {config.min_valid_fraction:.0%})")
    rows, cols, d = rows[valid], cols[valid], d[valid]
    points = backproject(cols, rows, d, geometry)

    z_median = float(np.median(points[:, 2]))
    axis2d = _image_axis(mask)
    half_width_px = _median_width(axis2d) / 2
    radius_guess_m = _radius_from_width(half_width_px, z_median, geometry.focal_px, config.erode_px)
    depth_noise_m = z_median ** 2 / geometry.fb * config.disparity_noise_px
    band_m = max(config.min_inlier_band_m, 3.0 * depth_noise_m, radius_guess_m)
    try:
        fit = fit_line_robust(points, band_m)
    except GeometryError as exc:
        return DroppedBranch(mask_id, f"no 3D line: {exc}")
    n_inliers = int(fit.inliers.sum())
    if n_inliers < config.min_points:
        return DroppedBranch(mask_id, f"line fit kept {n_inliers} points, fewer than {config.min_points}")

    slice_px = max(3.0, 0.15 * axis2d.length_px)
    low_is_base, base_at_trunk = _base_is_low_end(axis2d, trunk)
    elongated = axis2d.length_px >= 2.0 * max(1.0, 2.0 * half_width_px)
    line = fit.line
    if config.surface_correction:
        line = _pushed_back(line, radius_guess_m * _surface_offset_factor(half_width_px, config.erode_px))

    if elongated:
        base_px = _end_centre(axis2d, low_is_base, slice_px)
        tip_px = _end_centre(axis2d, not low_is_base, slice_px)
        base_m = line.closest_to_ray(pixel_ray(*base_px, geometry))
        tip_m = line.closest_to_ray(pixel_ray(*tip_px, geometry))
        if base_at_trunk and trunk_model is not None:
            # the mask's end is where the branch vanishes into the trunk's silhouette, which for a
            # branch pointing at or away from the camera is far from where it leaves the bark
            exit_m = trunk_model.exit_point(line, tip_m - base_m)
            if exit_m is not None and (np.linalg.norm(exit_m - base_m)
                                       < 0.5 * np.linalg.norm(tip_m - base_m) + 2.0 * trunk_model.radius_m):
                base_m = exit_m
    else:  # seen end-on: the silhouette has no ends; the deeper 3D end is the base
        t = line.parameters(points[fit.inliers])
        ends = line.at(np.quantile(t, [0.02, 0.98]))
        base_m, tip_m = (ends[0], ends[1]) if ends[0][2] >= ends[1][2] else (ends[1], ends[0])
    axis = line.direction if line.direction @ (tip_m - base_m) >= 0 else -line.direction
    cut_m = base_m + config.cut_offset_m * axis
    distance = float(np.linalg.norm(cut_m))
    if not config.min_range_m <= distance <= config.max_range_m:
        return DroppedBranch(mask_id, f"cut point at {distance:.2f} m is outside the working range "
                                      f"{config.min_range_m}–{config.max_range_m} m")
    if cut_m[2] <= 0:
        return DroppedBranch(mask_id, "cut point lies behind the camera")
    pixel = project(cut_m, geometry)[0]
    s_cut = float((pixel - axis2d.centre) @ axis2d.direction)
    s_cut = float(np.clip(s_cut, axis2d.s_lo + slice_px / 2, axis2d.s_hi - slice_px / 2)) if elongated else 0.0
    width_px = axis2d.width_near(s_cut, slice_px / 2)
    diameter = width_px * float(cut_m[2]) / geometry.focal_px

    stereo_conf = float(np.mean(confidence[rows, cols][fit.inliers])) if confidence is not None else 1.0
    if not np.isfinite(stereo_conf):
        stereo_conf = 0.0
    score = _confidence(valid_fraction, fit, band_m, stereo_conf, n_inliers, config)
    if score < config.min_confidence:
        return DroppedBranch(mask_id, f"confidence {score:.2f} below {config.min_confidence}")
    return BranchEstimate(
        mask_id=mask_id, cut_point_m=cut_m, base_m=base_m, axis=axis, distance_m=distance,
        pixel=(float(pixel[0]), float(pixel[1])), diameter_m=float(diameter), confidence=score,
        valid_fraction=valid_fraction, residual_m=fit.residual_m, n_points=n_inliers, id=mask_id,
    )


def estimate_cut_points(
    masks: BranchMasks,
    disparity: np.ndarray,
    geometry: StereoGeometry,
    config: CutPointConfig = CutPointConfig(),
    *,
    confidence: np.ndarray | None = None,
    max_disparity: float | None = None,
) -> CutPointResult:
    """Cut points of every branch instance in `masks` from the `H×W` disparity (px).

    Shapes must agree (the caller validates); `confidence` is the stereo confidence `H×W` in [0, 1].
    """
    disparity = np.asarray(disparity, dtype=np.float32)
    if disparity.shape != masks.shape:
        raise ValueError(f"disparity is {disparity.shape} but the mask is {masks.shape} (H, W)")
    trunk = masks.trunk()
    trunk_model = None if trunk is None else fit_trunk(trunk, disparity, geometry, config, max_disparity)
    result = CutPointResult()
    for mask_id in masks.branch_ids():
        outcome = estimate_branch(mask_id, masks.branch(mask_id), disparity, geometry, config,
                                  confidence=confidence, trunk=trunk, trunk_model=trunk_model,
                                  max_disparity=max_disparity)
        if isinstance(outcome, DroppedBranch):
            result.dropped.append(outcome)
        else:
            result.branches.append(outcome)
    return result


def select_target(
    branches: list[BranchEstimate],
    policy: TargetPolicy = "nearest",
    min_confidence: float = 0.3,
) -> BranchEstimate | None:
    """The branch a controller should approach, or None when no branch is confident enough.

    `nearest`: smallest distance; `most_confident`: highest confidence; `thickest`: largest
    diameter. Only branches with confidence ≥ `min_confidence` take part.
    """
    if policy not in TARGET_POLICIES:
        raise CutPointConfigError(f"target policy {policy!r} is not one of {', '.join(TARGET_POLICIES)}")
    candidates = [b for b in branches if b.confidence >= min_confidence]
    if not candidates:
        return None
    if policy == "nearest":
        return min(candidates, key=lambda b: b.distance_m)
    if policy == "most_confident":
        return max(candidates, key=lambda b: b.confidence)
    return max(candidates, key=lambda b: b.diameter_m)
