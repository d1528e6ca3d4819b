"""Training curves drawn with OpenCV (matplotlib is not a dependency): loss and validation EPE per epoch."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from stereo.io import write_rgb

_PANEL_W, _PANEL_H, _MARGIN = 480, 320, 50
_COLOURS = {"train_loss": (31, 119, 180), "val_epe": (214, 39, 40)}


def plot_panel(
    title: str, xs: Sequence[float], ys: Sequence[float], colour: tuple[int, int, int], x_label: str = "epoch"
) -> np.ndarray:
    """One RGB plot panel: axes, min/max labels, the polyline and its points (`None`/non-finite `ys` skipped)."""
    canvas = np.full((_PANEL_H, _PANEL_W, 3), 255, dtype=np.uint8)
    points = [(x, y) for x, y in zip(xs, ys) if y is not None and math.isfinite(y)]
    x0, y0, x1, y1 = _MARGIN, _PANEL_H - _MARGIN, _PANEL_W - 20, 30
    cv2.line(canvas, (x0, y0), (x1, y0), (0, 0, 0), 1)
    cv2.line(canvas, (x0, y0), (x0, y1), (0, 0, 0), 1)
    cv2.putText(canvas, title, (x0, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(canvas, x_label, (x1 - 50, y0 + 35), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    if not points:
        cv2.putText(canvas, "no data", (x0 + 20, (y0 + y1) // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
        return canvas
    px = np.array([p[0] for p in points], dtype=float)
    py = np.array([p[1] for p in points], dtype=float)
    lo_x, hi_x = px.min(), max(px.max(), px.min() + 1)
    lo_y, hi_y = py.min(), py.max()
    if hi_y - lo_y < 1e-12:
        lo_y, hi_y = lo_y - 0.5, hi_y + 0.5
    u = x0 + (px - lo_x) / (hi_x - lo_x) * (x1 - x0)
    v = y0 - (py - lo_y) / (hi_y - lo_y) * (y0 - y1)
    pixels = np.stack([u, v], axis=1).round().astype(np.int32)
    cv2.polylines(canvas, [pixels.reshape(-1, 1, 2)], False, colour, 2, cv2.LINE_AA)
    for u_i, v_i in pixels:
        cv2.circle(canvas, (int(u_i), int(v_i)), 3, colour, -1, cv2.LINE_AA)
    for value, row in ((hi_y, y1), (lo_y, y0)):
        cv2.putText(canvas, f"{value:.3g}", (2, row + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for value, col in ((lo_x, x0), (hi_x, x1)):
        cv2.putText(canvas, f"{value:g}", (col - 5, y0 + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas


def training_curve_image(history: Sequence[dict]) -> np.ndarray:
    """RGB `uint8` image with the training loss panel beside the validation EPE panel."""
    epochs = [row["epoch"] for row in history]
    panels = [
        plot_panel("train loss", epochs, [row.get("train_loss") for row in history], _COLOURS["train_loss"]),
        plot_panel("val EPE (px)", epochs, [row.get("val_epe") for row in history], _COLOURS["val_epe"]),
    ]
    return np.concatenate(panels, axis=1)


def write_training_curve(history: Sequence[dict], path: Path) -> Path:
    """Draw `training_curve_image(history)` to a PNG at `path`."""
    write_rgb(path, training_curve_image(history))
    return path
