"""A picture of one frame's result: the left image, branch masks, each cut point labelled with its
distance and confidence ("1.23 m · 87 %"), and the target ringed and labelled "TARGET": what an
operator checks at a glance. Labels never overlap each other or the status line and stay inside
the frame (`place_labels`); a label pushed away from its point keeps a leader line to it.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from branchrange.core.frame_result import Branch, FrameResult
from branchrange.core.geometry import StereoGeometry, project
from branchrange.core.masks import BranchMasks

_TARGET_RGB = (255, 40, 40)
_CUT_RGB = (255, 230, 0)
_TRUNK_RGB = (40, 160, 255)


def _instance_colour(instance_id: int) -> tuple[int, int, int]:
    """A distinct, stable RGB colour per instance id (golden-angle hue steps)."""
    hue = int((instance_id * 137.508) % 180)
    hsv = np.array([[[hue, 200, 255]]], dtype=np.uint8)
    r, g, b = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0]
    return int(r), int(g), int(b)


#: Label text sits this many px inside its box; boxes keep this many px from the frame edge.
_PAD = 3
_FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass(frozen=True)
class Box:
    """An axis-aligned pixel rectangle [x0, x1) × [y0, y1)."""

    x0: int
    y0: int
    x1: int
    y1: int

    def intersects(self, other: Box) -> bool:
        return self.x0 < other.x1 and other.x0 < self.x1 and self.y0 < other.y1 and other.y0 < self.y1

    def inside(self, width: int, height: int) -> bool:
        return self.x0 >= 0 and self.y0 >= 0 and self.x1 <= width and self.y1 <= height


def label_parts(branch: Branch, is_target: bool) -> list[str]:
    """What a person reads beside a cut point: distance in metres and confidence in percent,
    "TARGET" first on the target. The parts are drawn with a middle dot between them
    ("TARGET · 1.23 m · 87 %"): OpenCV's fonts have no "·", so the dot is drawn, not typed."""
    parts = [f"{branch.distance_m:.2f} m", f"{round(100 * branch.confidence)} %"]
    return ["TARGET", *parts] if is_target else parts


def _thickness(scale: float) -> int:
    return max(1, int(round(scale * 2)))


def _text_size(text: str, scale: float) -> tuple[int, int, int]:
    (width, height), baseline = cv2.getTextSize(text, _FONT, scale, _thickness(scale))
    return width, height, baseline


def _parts_size(parts: list[str], scale: float) -> tuple[int, int, int]:
    """(width, height, gap) of parts drawn in a row with a dot between each two, box padding included."""
    sizes = [_text_size(part, scale) for part in parts]
    gap = max(6, int(round(12 * scale)))
    width = sum(w for w, _, _ in sizes) + gap * (len(parts) - 1) + 2 * _PAD
    height = max(h + b for _, h, b in sizes) + 2 * _PAD
    return width, height, gap


def place_labels(
    anchors: list[tuple[int, int]],
    sizes: list[tuple[int, int]],
    frame: tuple[int, int],
    reserved: Sequence[Box] = (),
    clearance: int = 8,
) -> list[Box | None]:
    """Boxes for labels of `sizes` (w, h) px near `anchors` (u, v), inside `frame` (width, height),
    never intersecting each other nor `reserved`; None for a label no free place could take.

    Greedy, in the order given (put the target first): the first free candidate among boxes
    beside the anchor (right, left, above, below, `clearance` px from it), then the same
    directions ever further out, then any free slot of the frame, row by row; the caller draws
    a leader line to a label that ended up far from its point.
    """
    width, height = frame
    placed: list[Box] = list(reserved)
    boxes: list[Box | None] = []
    for (u, v), (w, h) in zip(anchors, sizes):
        box = next(
            (
                b
                for b in _candidates(u, v, w, h, width, height, clearance)
                if b.inside(width, height) and not any(b.intersects(p) for p in placed)
            ),
            None,
        )
        if box is not None:
            placed.append(box)
        boxes.append(box)
    return boxes


def _candidates(u: int, v: int, w: int, h: int, width: int, height: int, clearance: int) -> Iterator[Box]:
    """Boxes of size w×h to try for the label of anchor (u, v), nearest first (see `place_labels`)."""

    def at(x: int, y: int) -> Box:
        x = min(max(x, _PAD), width - w - _PAD)
        y = min(max(y, _PAD), height - h - _PAD)
        return Box(x, y, x + w, y + h)

    step = h + _PAD
    for ring in range(max(width, height) // step + 1):
        far = clearance + ring * step
        yield at(u + far, v - h - far // 2)  # right, above the point
        yield at(u + far, v + far // 2)  # right, below
        yield at(u - w - far, v - h - far // 2)  # left, above
        yield at(u - w - far, v + far // 2)  # left, below
        yield at(u - w // 2, v - h - far)  # straight above
        yield at(u - w // 2, v + far)  # straight below
    for y in range(_PAD, height - h - _PAD + 1, step):
        for x in range(_PAD, width - w - _PAD + 1, max(1, w // 4)):
            yield Box(x, y, x + w, y + h)


def _draw_label(image: np.ndarray, box: Box, parts: list[str], colour: tuple[int, int, int], scale: float) -> None:
    """Parts on a darkened box with a thin frame (drawn in place on RGB `image`), dots between them."""
    region = image[box.y0 : box.y1, box.x0 : box.x1]
    region[:] = (region * 0.35).astype(np.uint8)  # darken, so the text reads on any background
    cv2.rectangle(image, (box.x0, box.y0), (box.x1 - 1, box.y1 - 1), colour, 1, cv2.LINE_AA)
    _, _, gap = _parts_size(parts, scale)
    text_h = max(_text_size(part, scale)[1] for part in parts)
    baseline_y = box.y0 + _PAD + text_h
    x = box.x0 + _PAD
    for i, part in enumerate(parts):
        if i:
            dot = (x - gap // 2 - 1, baseline_y - text_h // 2)
            cv2.circle(image, dot, max(1, int(round(2 * scale))), colour, -1, cv2.LINE_AA)
        cv2.putText(image, part, (x, baseline_y), _FONT, scale, colour, _thickness(scale), cv2.LINE_AA)
        x += _text_size(part, scale)[0] + gap


def _nearest_point(box: Box, u: int, v: int) -> tuple[int, int]:
    return min(max(u, box.x0), box.x1 - 1), min(max(v, box.y0), box.y1 - 1)


def status_parts(result: FrameResult, unlabelled: int = 0) -> list[str]:
    """The status line: cut-point count, the target's distance (or "no target" and why), unlabelled count."""
    parts = [f"{len(result.branches)} cut points"]
    target = result.target
    if target is not None:
        parts.append(f"target {target.distance_m:.2f} m")
    else:
        parts.append("no target" + (f" ({result.reason[:60]})" if result.reason else ""))
    if unlabelled:
        parts.append(f"{unlabelled} unlabelled (no room)")
    return parts


def layout_labels(
    result: FrameResult, width: int, height: int, scale: float, clearance: int
) -> tuple[Box, list[tuple[Branch, list[str], Box | None]]]:
    """Where the status line and each branch's label go in a `width × height` frame.

    The status line takes the top-left corner and every cut point's marker (`clearance` px
    around it) stays uncovered; the labels follow, target first, then nearest first, placed by
    `place_labels`; a label with no free place gets None (the status line then counts them).
    """
    order = sorted(result.branches, key=lambda b: (not result.is_target(b), b.distance_m))
    parts = [label_parts(b, result.is_target(b)) for b in order]
    sizes = [_parts_size(p, scale)[:2] for p in parts]
    anchors = [_pixel(b) for b in order]
    markers = [
        Box(u - clearance // 2, v - clearance // 2, u + clearance // 2 + 1, v + clearance // 2 + 1) for u, v in anchors
    ]
    unlabelled = 0
    while True:  # at most twice: once more when the status line must grow to count unlabelled ones
        status_w, status_h, _ = _parts_size(status_parts(result, unlabelled), scale)
        status = Box(_PAD, _PAD, min(width, _PAD + status_w), min(height, _PAD + status_h))
        boxes = place_labels(anchors, sizes, (width, height), reserved=[status, *markers], clearance=clearance)
        missing = sum(box is None for box in boxes)
        if bool(missing) == bool(unlabelled):
            return status, list(zip(order, parts, boxes))
        unlabelled = max(missing, 1)


def _pixel(branch: Branch) -> tuple[int, int]:
    """The branch's cut pixel (u, v), rounded to the nearest pixel."""
    return int(round(branch.pixel[0])), int(round(branch.pixel[1]))


def _axis_stroke(branch: Branch, geometry: StereoGeometry) -> tuple[float, float] | None:
    """The image direction (du, dv) px of the branch's axis at its cut point (5 cm toward the tip,
    projected), or None when that stretch leaves the half-space in front of the camera."""
    cut, axis = np.asarray(branch.cut_point_m), np.asarray(branch.axis)
    if cut[2] <= 0 or cut[2] + 0.05 * axis[2] <= 0:
        return None
    start, end = project(np.stack([cut, cut + 0.05 * axis]), geometry)
    return float(end[0] - start[0]), float(end[1] - start[1])


def draw_overlay(
    left: np.ndarray, result: FrameResult, masks: BranchMasks | None = None, alpha: float = 0.45
) -> np.ndarray:
    """The overlay as RGB `uint8 H×W×3`: `left` (RGB `uint8 H×W×3`, rectified) with `masks` tinted,
    every branch of `result` marked at its cut pixel with its axis drawn and labelled with distance
    and confidence, and the target ringed in red and labelled TARGET."""
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
    geometry = result.camera.geometry()
    for branch in result.branches:
        colour = _TARGET_RGB if result.is_target(branch) else _CUT_RGB
        u, v = _pixel(branch)
        stroke = _axis_stroke(branch, geometry)
        if stroke is not None:  # the axis direction as a short stroke toward the tip
            norm = float(np.hypot(*stroke)) or 1.0
            end = (int(round(u + 3 * radius * stroke[0] / norm)), int(round(v + 3 * radius * stroke[1] / norm)))
            cv2.line(canvas, (u, v), end, _CUT_RGB, max(1, radius // 3), cv2.LINE_AA)
        cv2.circle(canvas, (u, v), radius, colour, max(1, radius // 3), cv2.LINE_AA)
        cv2.drawMarker(canvas, (u, v), colour, cv2.MARKER_CROSS, radius, 1, cv2.LINE_AA)
        if result.is_target(branch):
            cv2.circle(canvas, (u, v), 2 * radius + 2, _TARGET_RGB, max(2, radius // 2), cv2.LINE_AA)
    status_box, labels = layout_labels(result, canvas.shape[1], canvas.shape[0], scale, clearance=4 * radius + 6)
    unlabelled = sum(box is None for _, _, box in labels)
    _draw_label(canvas, status_box, status_parts(result, unlabelled), (255, 255, 255), scale)
    placed = [
        (branch, parts, box, _TARGET_RGB if result.is_target(branch) else _CUT_RGB)
        for branch, parts, box in labels
        if box is not None
    ]
    for branch, _, box, colour in placed:  # leader lines first, so labels cover lines, not the reverse
        u, v = _pixel(branch)
        near = _nearest_point(box, u, v)
        if np.hypot(near[0] - u, near[1] - v) > 3 * radius:  # a label pushed away keeps a line to its point
            cv2.line(canvas, (u, v), near, colour, 1, cv2.LINE_AA)
    for _, parts, box, colour in placed:
        _draw_label(canvas, box, parts, colour, scale)
    return canvas


def write_overlay(path: str | Path, left: np.ndarray, result: FrameResult, masks: BranchMasks | None = None) -> Path:
    """Draw the overlay and write it as PNG (or any format OpenCV knows by extension); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image = draw_overlay(left, result, masks)
    if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write the overlay image {path} (unknown extension or unwritable folder)")
    return path
