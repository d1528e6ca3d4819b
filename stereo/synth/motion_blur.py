"""Motion blur of a rendered view along its own image motion, from its depth and two camera poses.

A pixel's surface point X (from the view's depth, or a direction for the sky) was seen at
another pixel one frame earlier; the difference is the image motion m (px per frame interval).
While the shutter is open over the last `shutter` of the interval, the image content flows by
`−m·shutter` toward its final place, so pixel p gathered the content now found at `p − s·m`,
`0 ≤ s ≤ shutter`: the blurred image is the mean of the sharp image sampled there. Exact for a
locally uniform motion; at occlusion edges a pixel borrows its own motion for its neighbours.
"""

from __future__ import annotations

import cv2
import numpy as np

from stereo.synth.camera import SynthCamera

#: Most image samples averaged per pixel (bounds the cost: a remap of an HD720 view each).
MAX_SAMPLES = 8


def image_motion(
    depth_m: np.ndarray,
    camera: SynthCamera,
    view: str,
    now: tuple[np.ndarray, np.ndarray],
    before: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """Where each pixel's surface point was in the same view one step earlier, minus where it is now.

    `depth_m` float64 `H×W` (Z in m, inf on sky) of the 'left' or 'right' `view`; `now` and
    `before` are the rig's (rotation `(3, 3)`, position `(3,)`) poses, `X_world = R·X_cam + t`
    for the left camera. Returns float32 `H×W×2` (dx, dy) px; 0 where the point was behind the
    earlier camera.
    """
    (r_now, t_now), (r_before, t_before) = now, before
    offset = camera.origin(view)
    centre_now, centre_before = t_now + r_now @ offset, t_before + r_before @ offset
    rotate = r_before.T @ r_now
    shift = r_before.T @ (centre_now - centre_before)
    x = ((np.arange(camera.width) - camera.cx) / camera.focal_px).astype(np.float32)[None, :]
    y = ((np.arange(camera.height) - camera.cy) / camera.focal_px).astype(np.float32)[:, None]
    with np.errstate(divide="ignore"):
        inverse_depth = np.where(np.isfinite(depth_m) & (depth_m > 0), 1.0 / depth_m, 0.0).astype(np.float32)
    # X_before / Z_now for the ray (x, y, 1): the sky (1/Z = 0) moves by the rotation alone
    seen = [
        np.float32(row[0]) * x + np.float32(row[1]) * y + np.float32(row[2]) + np.float32(move) * inverse_depth
        for row, move in zip(rotate, shift)
    ]
    ahead = seen[2] > 1e-6
    z = np.where(ahead, seen[2], np.float32(1.0))
    f = np.float32(camera.focal_px)
    flow = np.stack([f * seen[0] / z - f * x, f * seen[1] / z - f * y], axis=-1)
    flow[~ahead] = 0.0
    return flow


def blur_along_motion(image: np.ndarray, motion: np.ndarray, shutter: float) -> np.ndarray:
    """`image` (float32 `H×W×C`) averaged along `−s·motion`, `0 ≤ s ≤ shutter` (see the module docstring).

    The number of samples follows the longest streak (about one per pixel of it), at most
    `MAX_SAMPLES`; a still image comes back unchanged.
    """
    streak = float(np.abs(motion).max()) * shutter if motion.size else 0.0
    samples = int(np.clip(np.ceil(streak) + 1, 1, MAX_SAMPLES))
    if samples == 1:
        return image
    height, width = image.shape[:2]
    grid_y, grid_x = np.mgrid[0:height, 0:width].astype(np.float32)
    total = np.zeros_like(image, dtype=np.float32)
    for s in np.linspace(0.0, shutter, samples, dtype=np.float32):
        total += cv2.remap(
            image,
            grid_x - s * motion[..., 0],
            grid_y - s * motion[..., 1],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).reshape(image.shape)
    return total / np.float32(samples)
