"""The rectified stereo rig the synthetic scenes are rendered with, and its rays.

Pixel centres sit at integer coordinates (OpenCV convention) and the principal point is the image
centre, `((W-1)/2, (H-1)/2)`. The left camera is the origin of the scene frame (x right, y down,
z forward, metres); the right camera sits at `(B, 0, 0)` with the same orientation, so a point at
depth Z appears `f·B/Z` pixels further left in the right image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stereo.pinhole import disparity_from_depth, project

#: The VirtualTree / ZED Mini rig: focal length in pixels at this width, baseline in metres.
ZED_MINI_FOCAL_PX_AT_1920 = 960.0
ZED_MINI_REFERENCE_WIDTH = 1920
ZED_MINI_BASELINE_M = 0.063


@dataclass(frozen=True)
class SynthCamera:
    """A rectified pinhole stereo pair: image size (px), focal length (px) and baseline (m)."""

    width: int
    height: int
    focal_px: float
    baseline_m: float

    def __post_init__(self) -> None:
        if int(self.width) != self.width or int(self.height) != self.height or self.width < 8 or self.height < 8:
            raise ValueError(f"SynthCamera: width and height must be integers ≥ 8 px, got {self.width}×{self.height}")
        if not (np.isfinite(self.focal_px) and self.focal_px > 0):
            raise ValueError(f"SynthCamera: focal_px must be a positive number of pixels, got {self.focal_px}")
        if not (np.isfinite(self.baseline_m) and self.baseline_m > 0):
            raise ValueError(f"SynthCamera: baseline_m must be a positive number of metres, got {self.baseline_m}")

    @classmethod
    def zed_mini(cls, width: int = 1280, height: int = 720) -> SynthCamera:
        """The ZED Mini rig of VirtualTree (f = 960 px at 1920 px width, B = 0.063 m) scaled to `width`."""
        return cls(width, height, ZED_MINI_FOCAL_PX_AT_1920 * width / ZED_MINI_REFERENCE_WIDTH, ZED_MINI_BASELINE_M)

    @property
    def cx(self) -> float:
        """Principal point x in pixels (the image centre)."""
        return (self.width - 1) / 2.0

    @property
    def cy(self) -> float:
        """Principal point y in pixels (the image centre)."""
        return (self.height - 1) / 2.0

    def origin(self, view: str) -> np.ndarray:
        """Optical centre of the 'left' or 'right' camera in the left camera frame, metres `(3,)`."""
        if view == "left":
            return np.zeros(3)
        if view == "right":
            return np.array([self.baseline_m, 0.0, 0.0])
        raise ValueError(f"view must be 'left' or 'right', got {view!r}")

    def project(self, points_m: np.ndarray, view: str = "left") -> np.ndarray:
        """Pixel coordinates `(N, 2)` of points `(N, 3)` (metres, left camera frame) seen from `view`."""
        pts = np.atleast_2d(np.asarray(points_m, dtype=np.float64)) - self.origin(view)
        return project(pts, self.focal_px, self.cx, self.cy)

    def disparity_from_depth(self, depth_m: np.ndarray) -> np.ndarray:
        """Disparity `f·B/Z` (px, float32) of a depth map (m); non-finite or non-positive depth gives 0."""
        depth = np.asarray(depth_m, dtype=np.float64)
        valid = np.isfinite(depth) & (depth > 0)
        disparity = np.zeros(depth.shape, dtype=np.float32)
        disparity[valid] = disparity_from_depth(depth[valid], self.focal_px, self.baseline_m)
        return disparity

    def to_dict(self) -> dict[str, float | int]:
        """The rig as JSON-ready values (the branches files carry it)."""
        return {
            "width": self.width,
            "height": self.height,
            "focal_px": self.focal_px,
            "baseline_m": self.baseline_m,
            "cx": self.cx,
            "cy": self.cy,
        }


@dataclass(frozen=True)
class RayGrid:
    """Rays of one view through a regular grid of sample positions (`samples`² per pixel).

    Ray `(i, j)` leaves `origin` with direction `(dx[j], dy[i], 1)`: its parameter t is the depth Z
    of the point it reaches. `dx`, `dy` are float64 `(Ws,)`, `(Hs,)` with `Ws = W·samples`.
    """

    origin: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    samples: int
    focal_px: float
    cx: float
    cy: float

    @classmethod
    def for_view(cls, camera: SynthCamera, view: str, samples: int) -> RayGrid:
        """Rays through `samples × samples` evenly spaced points in each pixel (1 → the pixel centres)."""
        offsets = (np.arange(samples) + 0.5) / samples - 0.5
        xs = (np.arange(camera.width)[:, None] + offsets[None, :]).ravel()
        ys = (np.arange(camera.height)[:, None] + offsets[None, :]).ravel()
        return cls(
            camera.origin(view),
            (xs - camera.cx) / camera.focal_px,
            (ys - camera.cy) / camera.focal_px,
            samples,
            camera.focal_px,
            camera.cx,
            camera.cy,
        )

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns) of the sample grid."""
        return self.dy.size, self.dx.size

    def sample_boxes(self, hulls_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Sample-index boxes `[r0, r1) × [c0, c1)` (int64 `(K,)` each) whose rays can meet each hull.

        `hulls_m` `(K, M, 3)`: points whose convex hull contains primitive k. A hull reaching
        behind the near plane gets the whole grid (conservative); an empty box has r0 == r1.
        """
        rel = np.asarray(hulls_m, dtype=np.float64) - self.origin
        z = rel[..., 2]
        behind = np.any(z <= 1e-3, axis=1)
        z_safe = np.where(z > 1e-3, z, 1.0)
        u = self.focal_px * rel[..., 0] / z_safe + self.cx
        v = self.focal_px * rel[..., 1] / z_safe + self.cy
        rows, cols = self.shape
        s = self.samples
        c0 = np.clip(np.floor((u.min(axis=1) + 0.5) * s - 0.5), 0, cols).astype(np.int64)
        c1 = np.clip(np.ceil((u.max(axis=1) + 0.5) * s - 0.5) + 1, 0, cols).astype(np.int64)
        r0 = np.clip(np.floor((v.min(axis=1) + 0.5) * s - 0.5), 0, rows).astype(np.int64)
        r1 = np.clip(np.ceil((v.max(axis=1) + 0.5) * s - 0.5) + 1, 0, rows).astype(np.int64)
        c0[behind], c1[behind], r0[behind], r1[behind] = 0, cols, 0, rows
        empty = (c0 >= c1) | (r0 >= r1) | np.all(z <= 1e-3, axis=1)
        r1[empty] = r0[empty]
        return r0, r1, c0, c1


def enumerate_boxes(
    r0: np.ndarray, r1: np.ndarray, c0: np.ndarray, c1: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every sample of K boxes as flat arrays `(part, row, col)`, `part` being the box index (0..K-1)."""
    heights = np.maximum(r1 - r0, 0)
    widths = np.where(heights > 0, c1 - c0, 0)
    sizes = heights * widths
    part = np.repeat(np.arange(sizes.size), sizes)
    local = np.arange(part.size) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    w = widths[part]
    return part, r0[part] + local // w, c0[part] + local % w
