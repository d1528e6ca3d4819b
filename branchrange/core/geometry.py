"""Stereo geometry for cut points: disparity → 3D points, projection, and a robust 3D line fit.

Frames and units (design.md): 3D points are metres in the rectified left camera frame with OpenCV
axes (x right, y down, z forward); pixels are (u, v) = (column, row) of the rectified left image at
the resolution the disparity was computed; disparity is in pixels, positive, left reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stereo import pinhole
from stereo.pinhole import ArrayOrFloat


class GeometryError(ValueError):
    """Camera parameters or point sets that cannot give a meaningful 3D result."""


@dataclass(frozen=True)
class StereoGeometry:
    """Pinhole model of a rectified stereo pair.

    `focal_px` is the rectified focal length in pixels at the disparity's resolution, `baseline_m`
    the distance between the optical centres in metres, `(cx, cy)` the principal point in pixels.
    """

    focal_px: float
    baseline_m: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        for name in ("focal_px", "baseline_m", "cx", "cy"):
            value = getattr(self, name)
            if not np.isfinite(value):
                raise GeometryError(f"StereoGeometry.{name} = {value!r} is not a finite number")
        if self.focal_px <= 0:
            raise GeometryError(f"StereoGeometry.focal_px = {self.focal_px!r} must be > 0 (pixels)")
        if self.baseline_m <= 0:
            raise GeometryError(f"StereoGeometry.baseline_m = {self.baseline_m!r} must be > 0 (metres)")

    @classmethod
    def centred(cls, focal_px: float, baseline_m: float, width: int, height: int) -> StereoGeometry:
        """A geometry whose principal point is the image centre, for when only f and B are known."""
        return cls(float(focal_px), float(baseline_m), (width - 1) / 2.0, (height - 1) / 2.0)

    @property
    def fb(self) -> float:
        """f·B in pixel·metres: depth Z = fb / disparity."""
        return self.focal_px * self.baseline_m


def vector_norm(vector: np.ndarray) -> float:
    """Euclidean length of a 1-D vector: `np.linalg.norm`'s own arithmetic (√(v·v)), bit for bit,
    without its dispatch — the geometry takes thousands of them per frame on 2- and 3-vectors."""
    vector = np.asarray(vector, dtype=np.float64)
    return math.sqrt(vector.dot(vector))


def valid_disparity(disparity: np.ndarray, max_disparity: float | None = None) -> np.ndarray:
    """Boolean `H×W` mask of usable disparities: finite, > 0 and, when given, < `max_disparity`."""
    disparity = np.asarray(disparity)
    with np.errstate(invalid="ignore"):
        valid: np.ndarray = np.isfinite(disparity) & (disparity > 0)
        if max_disparity is not None:
            valid &= disparity < max_disparity
    return valid


def offset_disparity(disparity: np.ndarray, doffs_px: float) -> np.ndarray:
    """`d + doffs` where `disparity` (`H×W` px) is valid, 0 elsewhere: the disparity `Z = f·B/d` holds for.

    Middlebury 2014 pairs are rectified with the right principal point `doffs` px right of the
    left one, so depth is `Z = f·B/(d + doffs)`. Shifting the measured disparity once, at the
    pipeline's entry, keeps every later stage (segmenter, the disparity-space line fits of the cut
    points, cross-sections) exact without a second formula: a 3D line is a line in (u, v, d + doffs).
    """
    disparity = np.asarray(disparity, dtype=np.float32)
    if not np.isfinite(doffs_px):
        raise GeometryError(f"doffs = {doffs_px!r} must be a finite number of pixels")
    valid = valid_disparity(disparity)
    return np.where(valid, disparity + np.float32(doffs_px), 0.0).astype(np.float32)


def disparity_to_depth(disparity: np.ndarray, geometry: StereoGeometry) -> np.ndarray:
    """Depth `Z = f·B/d` in metres (`float32`, same shape as `disparity` in px); inf where invalid.

    Divided in place where valid (`np.divide(where=)`), not gathered and scattered by a boolean index: the
    instance step converts a whole HD720 frame twice a frame, most of it valid."""
    disparity = np.asarray(disparity, dtype=np.float32)
    depth = np.full(disparity.shape, np.inf, dtype=np.float32)
    focal_baseline = pinhole.depth_from_disparity(1.0, geometry.focal_px, geometry.baseline_m)  # f·B
    np.divide(focal_baseline, disparity, out=depth, where=valid_disparity(disparity))
    return depth


def backproject(u: np.ndarray, v: np.ndarray, disparity: np.ndarray, geometry: StereoGeometry) -> np.ndarray:
    """3D points `(N, 3)` in metres from pixel coordinates `u, v` `(N,)` and disparities `(N,)` in px.

    The caller passes only valid (positive, finite) disparities; `Z = f·B/d`, `X = (u − cx)·Z/f`,
    `Y = (v − cy)·Z/f`.
    """
    d = np.asarray(disparity, dtype=np.float64)
    if d.size and not (np.all(np.isfinite(d)) and np.all(d > 0)):
        raise GeometryError("backproject needs finite, positive disparities; filter with valid_disparity first")
    z = pinhole.depth_from_disparity(d, geometry.focal_px, geometry.baseline_m)
    x = (np.asarray(u, dtype=np.float64) - geometry.cx) * z / geometry.focal_px
    y = (np.asarray(v, dtype=np.float64) - geometry.cy) * z / geometry.focal_px
    return np.stack([x, y, z], axis=-1)


def project(points: np.ndarray, geometry: StereoGeometry) -> np.ndarray:
    """Pixel coordinates `(N, 2)` as (u, v) of 3D points `(N, 3)` in metres (z must be > 0)."""
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    if np.any(points[:, 2] <= 0):
        raise GeometryError("cannot project points at or behind the camera (z <= 0)")
    return pinhole.project(points, geometry.focal_px, geometry.cx, geometry.cy)


def pixel_ray(u: float, v: float, geometry: StereoGeometry) -> np.ndarray:
    """Unit direction `(3,)` of the viewing ray through pixel (u, v), from the left camera centre."""
    ray = np.array([(u - geometry.cx) / geometry.focal_px, (v - geometry.cy) / geometry.focal_px, 1.0])
    return ray / vector_norm(ray)


def pixel_rays(pixels: np.ndarray, geometry: StereoGeometry) -> np.ndarray:
    """Unit directions `(N, 3)` of the viewing rays through pixels `(N, 2)` (u, v): `pixel_ray`
    for many pixels in one step (equal to it within a few ulp)."""
    pixels = np.asarray(pixels, dtype=np.float64)
    rays = np.empty((len(pixels), 3))
    rays[:, 0] = (pixels[:, 0] - geometry.cx) / geometry.focal_px
    rays[:, 1] = (pixels[:, 1] - geometry.cy) / geometry.focal_px
    rays[:, 2] = 1.0
    unit: np.ndarray = rays / np.sqrt(np.einsum("nc,nc->n", rays, rays))[:, None]
    return unit


@dataclass(frozen=True)
class Line3D:
    """A 3D line `point + t·direction` (metres; `direction` is a unit vector `(3,)`)."""

    point: np.ndarray
    direction: np.ndarray

    def distances(self, points: np.ndarray) -> np.ndarray:
        """Perpendicular distance `(N,)` in metres of each point `(N, 3)` from the line."""
        offsets = np.asarray(points, dtype=np.float64) - self.point
        along = offsets @ self.direction
        distances: np.ndarray = np.linalg.norm(offsets - along[:, None] * self.direction, axis=1)
        return distances

    def parameters(self, points: np.ndarray) -> np.ndarray:
        """Signed position `t` `(N,)` in metres of each point's foot on the line."""
        t: np.ndarray = (np.asarray(points, dtype=np.float64) - self.point) @ self.direction
        return t

    def at(self, t: float | np.ndarray) -> np.ndarray:
        """The point(s) `point + t·direction` (`(3,)` or `(N, 3)`)."""
        t = np.asarray(t, dtype=np.float64)
        points: np.ndarray = self.point + t[..., None] * self.direction
        return points

    def closest_to_ray(self, ray_direction: np.ndarray) -> np.ndarray:
        """The point `(3,)` of this line closest to the ray from the origin along `ray_direction`.

        Used to lift a pixel (a mask end) onto the fitted axis; falls back to the foot of the ray
        origin when line and ray are parallel.
        """
        r = np.asarray(ray_direction, dtype=np.float64)
        r = r / vector_norm(r)
        d = self.direction
        w0 = self.point  # line point minus ray origin (the camera centre, 0)
        b = float(d @ r)
        denom = 1.0 - b * b
        if denom < 1e-9:
            return self.at(-float(w0 @ d))
        t = (b * float(w0 @ r) - float(w0 @ d)) / denom
        return self.at(t)


@dataclass(frozen=True)
class LineFit:
    """Result of `fit_line_robust`: the line, which input points were inliers, and the fit quality.

    `residual_m` is the RMS perpendicular distance of the inliers in metres; `inliers` is a boolean
    `(N,)` mask over the input points.
    """

    line: Line3D
    inliers: np.ndarray
    residual_m: float

    @property
    def inlier_fraction(self) -> float:
        """Share of the input points the fit kept, in [0, 1]."""
        return float(self.inliers.mean()) if self.inliers.size else 0.0


def _principal_line(points: np.ndarray, weights: np.ndarray | None = None) -> Line3D:
    """Weighted least-squares (orthogonal) line through `(N, 3)` points: centroid + top eigenvector."""
    if weights is None:
        weights = np.ones(len(points))
    w = weights / weights.sum()
    centroid = w @ points
    centred = points - centroid
    scatter = (centred * w[:, None]).T @ centred
    _, vectors = np.linalg.eigh(scatter)
    direction = vectors[:, -1]
    return Line3D(centroid, direction / vector_norm(direction))


def fit_line_robust(
    points: np.ndarray,
    inlier_threshold_m: float,
    *,
    iterations: int = 200,
    irls_steps: int = 5,
    seed: int = 0,
    score_points: int = 1500,
) -> LineFit:
    """Robust 3D line through `(N, 3)` points in metres: RANSAC on point pairs, then IRLS refit.

    Why robust: branch points come with silhouette and occlusion outliers (background or trunk depth
    bleeding into the mask) as the normal case. RANSAC picks the pair-line with most points within
    `inlier_threshold_m`; IRLS then re-weights all points with Tukey's biweight of their distance
    (scale = `inlier_threshold_m`), and a last plain least-squares fit runs over the points within
    the threshold.
    Candidates are scored on at most `score_points` random points. Deterministic for a given
    `seed`. Needs at least 2 distinct points.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise GeometryError(f"fit_line_robust expects points of shape (N, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise GeometryError("fit_line_robust got non-finite points")
    if inlier_threshold_m <= 0:
        raise GeometryError(f"inlier_threshold_m = {inlier_threshold_m!r} must be > 0 (metres)")
    n = len(points)
    if n < 2 or np.ptp(points, axis=0).max() == 0:
        raise GeometryError(f"a line needs at least 2 distinct points, got {n}")

    rng = np.random.default_rng(seed)
    # score candidate lines on at most `score_points` points, all candidates at once
    scored = points if n <= score_points else points[rng.choice(n, score_points, replace=False)]
    pairs = rng.integers(0, n, size=(iterations, 2))
    starts, deltas = points[pairs[:, 0]], points[pairs[:, 1]] - points[pairs[:, 0]]
    norms = np.linalg.norm(deltas, axis=1)
    usable = norms > 1e-9
    if usable.any():
        starts, directions = starts[usable], deltas[usable] / norms[usable, None]
        offsets = scored[None, :, :] - starts[:, None, :]
        perpendicular = np.cross(offsets, directions[:, None, :])
        counts = np.count_nonzero(
            np.einsum("kmc,kmc->km", perpendicular, perpendicular) < inlier_threshold_m**2, axis=1
        )
        best = int(np.argmax(counts))
        best_line = Line3D(starts[best], directions[best])
    else:  # every sampled pair coincided: fall back to the plain fit
        best_line = _principal_line(points)

    line = best_line
    for _ in range(irls_steps):
        r = line.distances(points) / inlier_threshold_m
        weights = np.where(r < 1.0, (1.0 - r * r) ** 2, 0.0)
        if np.count_nonzero(weights) < 2:
            break
        line = _principal_line(points, weights)

    inliers = line.distances(points) < inlier_threshold_m
    if np.count_nonzero(inliers) >= 2 and np.ptp(points[inliers], axis=0).max() > 0:
        # plain least squares over the inliers: the weights served to find them, but would pull the
        # line toward the densest part of a thick point cloud (a cylinder's front, not its centroid)
        line = _principal_line(points[inliers])
        inliers = line.distances(points) < inlier_threshold_m
    if np.count_nonzero(inliers) >= 2:
        residual = float(np.sqrt(np.mean(line.distances(points[inliers]) ** 2)))
    else:
        residual = float("inf")
    return LineFit(line, inliers, residual)


#: Residuals (float64) scored per block: blocks of candidates × samples that stay in the CPU cache.
_SCORE_BLOCK = 1 << 15


def _band_scores(
    x: np.ndarray, y: np.ndarray, slopes: np.ndarray, intercepts: np.ndarray, threshold: float, penalty_above: float
) -> np.ndarray:
    """RANSAC score `(K,)` of each candidate line `intercepts + slopes·x`: the samples `(N,)` within
    `threshold` of it, less `penalty_above` per sample `threshold` or more above it.

    Residuals are the same float64 expression as one `K×N` broadcast, evaluated a cache-sized block
    of candidates at a time into reused buffers (the counts, hence the chosen line, are exact):
    within = #(r < t) − #(r ≤ −t) and above = N − #(r < t) (t > 0, all values finite).
    """
    scores = np.zeros(slopes.size, dtype=np.float64)
    step = max(1, _SCORE_BLOCK // max(x.size, 1))
    buffer = np.empty((min(step, slopes.size), x.size))
    flags = np.empty(buffer.shape, dtype=bool)

    def count(block: np.ndarray) -> np.ndarray | int:  # one flat count is far faster than a count per row
        return int(np.count_nonzero(block)) if len(block) == 1 else np.count_nonzero(block, axis=1)

    for start in range(0, slopes.size, step):
        stop = min(start + step, slopes.size)
        residuals, flag = buffer[: stop - start], flags[: stop - start]
        np.multiply(slopes[start:stop, None], x[None, :], out=residuals)
        np.add(intercepts[start:stop, None], residuals, out=residuals)
        np.subtract(y[None, :], residuals, out=residuals)
        below_top = count(np.less(residuals, threshold, out=flag))
        below_bottom = count(np.less_equal(residuals, -threshold, out=flag))
        above = x.size - below_top if penalty_above > 0 else 0
        scores[start:stop] = (below_top - below_bottom) - penalty_above * above
    return scores


@dataclass(frozen=True)
class LinearFit:
    """`y ≈ intercept + slope·x` from `fit_linear_robust`, with its inliers (boolean `(N,)`) and
    the RMS residual of the inliers (units of y)."""

    slope: float
    intercept: float
    inliers: np.ndarray
    residual: float

    def at(self, x: ArrayOrFloat) -> ArrayOrFloat:
        """The fitted y at `x`."""
        return self.intercept + self.slope * x

    @property
    def inlier_fraction(self) -> float:
        """Share of the input samples the fit kept, in [0, 1]."""
        return float(self.inliers.mean()) if self.inliers.size else 0.0


def fit_linear_robust(
    x: np.ndarray, y: np.ndarray, threshold: float, *, iterations: int = 100, penalty_above: float = 0.0, seed: int = 0
) -> LinearFit:
    """Robust straight line `y(x)` through samples `(N,)`: RANSAC on pairs, least squares on inliers.

    Used for disparity along a branch's image axis: a 3D line maps to a line in (u, v, d) space
    (the map (X, Y, Z) → (u, v, d) is projective), so along the silhouette's centreline disparity
    is linear in position, and its noise is about constant in pixels — a far better conditioned
    fit than in metres, where depth noise grows with Z². `threshold` is the largest inlier
    residual (units of y). `penalty_above` > 0 scores a candidate down by that much for every
    sample more than `threshold` above it: for disparity inside a visible branch's mask, a sample
    nearer than the branch contradicts its visibility, while one farther is the usual background
    bleeding into a thin silhouette — so the near consensus wins over a larger far one.
    Needs two samples at distinct x.
    """
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise GeometryError(f"fit_linear_robust needs two equal (N,) arrays, got {x.shape} and {y.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise GeometryError("fit_linear_robust got non-finite samples")
    if threshold <= 0:
        raise GeometryError(f"threshold = {threshold!r} must be > 0")
    if x.size < 2 or np.ptp(x) == 0:
        raise GeometryError(f"a line needs samples at 2 distinct positions, got {x.size}")
    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, x.size, size=(2, iterations))
    usable = x[i] != x[j]
    i, j = i[usable], j[usable]
    slopes = (y[j] - y[i]) / (x[j] - x[i])
    intercepts = y[i] - slopes * x[i]
    scores = _band_scores(x, y, slopes, intercepts, threshold, penalty_above)
    best = int(np.argmax(scores)) if scores.size else -1
    slope, intercept = (slopes[best], intercepts[best]) if best >= 0 else np.polyfit(x, y, 1)
    inliers = np.abs(y - (intercept + slope * x)) < threshold
    for _ in range(3):  # refit on the inliers until they settle
        if np.count_nonzero(inliers) < 2 or np.ptp(x[inliers]) == 0:
            break
        slope, intercept = np.polyfit(x[inliers], y[inliers], 1)
        updated = np.abs(y - (intercept + slope * x)) < threshold
        if np.array_equal(updated, inliers):
            break
        inliers = updated
    residual = (
        float(np.sqrt(np.mean((y[inliers] - (intercept + slope * x[inliers])) ** 2))) if inliers.any() else float("inf")
    )
    return LinearFit(float(slope), float(intercept), inliers, residual)
