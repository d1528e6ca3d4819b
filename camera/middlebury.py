"""Middlebury 2014 `calib.txt`: a rectified pair's intrinsics, baseline (mm) and disparity offset `doffs`.

The file holds `key=value` lines: `cam0=[f 0 cx0; 0 f cy; 0 0 1]`, `cam1=[...]` (same form),
`doffs` (= cx1 − cx0, pixels), `baseline` (millimetres), `width`, `height` (pixels), and a few
keys not needed here (`ndisp`, `isint`, `vmin`, `vmax`, `dyavg`, `dymax`). Depth is
`Z = baseline · f / (d + doffs)`: the right camera's principal point sits `doffs` px right of the
left's, so the returned calibration keeps both principal points (`K2[0, 2] − K1[0, 2]` = doffs).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from camera.calibration import CalibrationError, StereoCalibration, from_rectified, read_calibration_text

REQUIRED_KEYS = ("cam0", "cam1", "baseline", "width", "height")


def _matrix(path: str | Path, key: str, text: str) -> np.ndarray:
    """A `[a b c; d e f; g h i]` value as a 3×3 array."""
    try:
        rows = [[float(v) for v in row.split()] for row in text.strip().strip("[]").split(";")]
        matrix = np.array(rows, dtype=np.float64)
    except ValueError:
        matrix = np.zeros(0)
    if matrix.shape != (3, 3):
        raise CalibrationError(path, key, f"is {text!r}", "a 3×3 matrix written [f 0 cx; 0 f cy; 0 0 1]")
    return matrix


def from_middlebury_calib(path: str | Path) -> StereoCalibration:
    """The rectified calibration a Middlebury 2014 `calib.txt` describes (baseline converted to metres)."""
    values = {}
    for line in read_calibration_text(path).splitlines():
        if "=" in line:
            key, _, value = line.partition("=")
            values[key.strip().lower()] = value.strip()
    for key in REQUIRED_KEYS:
        if key not in values:
            raise CalibrationError(
                path, key, "is missing", "a Middlebury calib.txt with cam0, cam1, baseline, width, height"
            )
    k0, k1 = _matrix(path, "cam0", values["cam0"]), _matrix(path, "cam1", values["cam1"])
    try:
        baseline_mm = float(values["baseline"])
        size = (int(float(values["width"])), int(float(values["height"])))
        doffs = float(values.get("doffs", k1[0, 2] - k0[0, 2]))
    except ValueError as exc:
        raise CalibrationError(path, "baseline/width/height/doffs", f"is not a number ({exc})", "numbers") from None
    if not np.isclose(doffs, k1[0, 2] - k0[0, 2], atol=0.01):
        raise CalibrationError(
            path, "doffs", f"is {doffs} but cam1 cx − cam0 cx is {k1[0, 2] - k0[0, 2]}", "doffs = cx1 − cx0 (pixels)"
        )
    if not (np.isclose(k0[0, 0], k1[0, 0]) and np.isclose(k0[1, 2], k1[1, 2])):
        raise CalibrationError(
            path,
            "cam1",
            "has another focal length or cy than cam0",
            "a rectified pair (same f and cy in cam0 and cam1)",
        )
    return from_rectified(k0[0, 0], k0[0, 2], k0[1, 2], baseline_mm / 1000.0, size, cx_right=k1[0, 2], source=str(path))
