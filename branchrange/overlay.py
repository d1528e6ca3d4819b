"""A picture of one frame's result: the left image, branch masks, each cut point labelled with its
distance and diameter, and the target highlighted — what an operator checks at a glance."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from branchrange.masks import BranchMasks

_TARGET_RGB = (255, 40, 40)
_CUT_RGB = (255, 230, 0)
_TRUNK_RGB = (40, 160, 255)


def _instance_colour(instance_id: int) -> tuple[int, int, int]:
    """A distinct, stable RGB colour per instance id (golden-angle hue steps)."""
    hue = int((instance_id * 137.508) % 180)
    hsv = np.uint8([[[hue, 200, 255]]])
    r, g, b = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0]
    return int(r), int(g), int(b)


def _label(image: np.ndarray, text: str, at: tuple[int, int], colour: tuple[int, int, int], scale: float) -> None:
    """Text with a dark outline so it reads on any background (drawn in place on RGB `image`)."""
    thickness = max(1, int(round(scale * 2)))
    cv2.putText(image, text, at, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), thickness + 2, cv2.LINE_AA)
    cv2.putText(image, text, at, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thickness, cv2.LINE_AA)


def draw_overlay(left: np.ndarray, result: dict, masks: BranchMasks | None = None, alpha: float = 0.45) -> np.ndarray:
    """The overlay as RGB `uint8 H×W×3`: `left` (RGB `uint8 H×W×3`, rectified) with `masks` tinted,
    every branch of `result` (a `branchrange/v1` dict) marked at its cut pixel with its id,
    distance and diameter, its axis drawn, and the target ringed in red."""
    canvas = left.copy()
    if masks is not None and masks.shape == left.shape[:2]:
        tint = np.zeros_like(canvas)
        painted = np.zeros(masks.shape, dtype=bool)
        for instance_id in masks.branch_ids():
            region = masks.branch(instance_id)
            tint[region] = _instance_colour(instance_id)
            painted |= region
        trunk = masks.trunk()
        if trunk is not None:
            tint[trunk] = _TRUNK_RGB
            painted |= trunk
        blended = (canvas * (1 - alpha) + tint * alpha).astype(np.uint8)
        canvas[painted] = blended[painted]
    scale = max(0.35, left.shape[1] / 1600.0)
    radius = max(4, left.shape[1] // 160)
    focal = float(result["camera"]["focal_px"])
    for branch in result.get("branches", []):
        is_target = branch["id"] == result.get("target_id")
        u, v = (int(round(c)) for c in branch["pixel"])
        x, y, z = branch["cut_point_m"]
        ax, ay, az = branch["axis"]
        if z + 0.05 * az > 0:  # the axis direction as a short stroke toward the tip
            tip = (focal * (x + 0.05 * ax) / (z + 0.05 * az) - focal * x / z, focal * (y + 0.05 * ay) / (z + 0.05 * az) - focal * y / z)
            norm = float(np.hypot(*tip)) or 1.0
            end = (int(round(u + 3 * radius * tip[0] / norm)), int(round(v + 3 * radius * tip[1] / norm)))
            cv2.line(canvas, (u, v), end, _CUT_RGB, max(1, radius // 3), cv2.LINE_AA)
        colour = _TARGET_RGB if is_target else _CUT_RGB
        cv2.circle(canvas, (u, v), radius, colour, max(1, radius // 3), cv2.LINE_AA)
        cv2.drawMarker(canvas, (u, v), colour, cv2.MARKER_CROSS, radius, 1, cv2.LINE_AA)
        if is_target:
            cv2.circle(canvas, (u, v), 2 * radius + 2, _TARGET_RGB, max(2, radius // 2), cv2.LINE_AA)
        text = f"#{branch['id']} {branch['distance_m']:.2f} m  d {branch['diameter_m'] * 1000:.0f} mm"
        _label(canvas, text, (u + radius + 3, v - radius - 2), colour, scale)
    status = f"{len(result.get('branches', []))} cut points"
    status += f", target #{result['target_id']}" if result.get("target_id") is not None else ", no target"
    if result.get("reason"):
        status += f" ({result['reason'][:80]})"
    _label(canvas, status, (6, int(22 * scale / 0.5)), (255, 255, 255), scale)
    return canvas


def write_overlay(path: str | Path, left: np.ndarray, result: dict, masks: BranchMasks | None = None) -> Path:
    """Draw the overlay and write it as PNG (or any format OpenCV knows by extension); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image = draw_overlay(left, result, masks)
    if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write the overlay image {path} (unknown extension or unwritable folder)")
    return path
