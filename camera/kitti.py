"""KITTI `calib_cam_to_cam.txt`: the rectified projections `P_rect_XX` of an already rectified pair.

Lines `KEY: v1 v2 …`; `P_rect_XX` is a 3×4 row-major projection of camera XX into the rectified
frame of camera 00, `S_rect_XX` the rectified image size (w, h). With `P = K [I | t]` the
baseline between two cameras is `(P_left[0,3] - P_right[0,3]) / fx` (0.5327 m for 02→03).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from camera.calibration import CalibrationError, StereoCalibration, from_rectified, parse_number, read_calibration_text


def parse_kitti(path: str | Path) -> dict[str, list[str]]:
    """The `KEY: values` lines of a KITTI calibration file as {KEY: [value strings]}."""
    entries: dict[str, list[str]] = {}
    for line in read_calibration_text(path).splitlines():
        key, sep, rest = line.partition(":")
        if sep and key.strip():
            entries[key.strip()] = rest.split()
    return entries


def _numbers(entries: dict[str, list[str]], key: str, count: int, path: Path) -> np.ndarray:
    if key not in entries:
        have = sorted(k for k in entries if k.startswith(key.split("_")[0]))
        raise CalibrationError(path, key, "key is missing", f"{count} numbers (file has {', '.join(have) or 'none'})")
    values = entries[key]
    if len(values) != count:
        raise CalibrationError(path, key, f"has {len(values)} values", f"{count} numbers")
    return np.array([parse_number(path, key, v) for v in values])


def from_kitti(path: str | Path, left: str = "02", right: str = "03") -> StereoCalibration:
    """Load the rectified pair `left`/`right` (camera numbers "00".."03") of a KITTI cam_to_cam file."""
    path = Path(path)
    entries = parse_kitti(path)
    p_left = _numbers(entries, f"P_rect_{left}", 12, path).reshape(3, 4)
    p_right = _numbers(entries, f"P_rect_{right}", 12, path).reshape(3, 4)
    width, height = _numbers(entries, f"S_rect_{left}", 2, path)
    fx = p_left[0, 0]
    if fx <= 0 or not np.isclose(p_right[0, 0], fx, rtol=1e-6) or not np.isclose(p_right[1, 2], p_left[1, 2]):
        raise CalibrationError(
            path,
            f"P_rect_{right}",
            f"fx={p_right[0, 0]}, cy={p_right[1, 2]} differ from P_rect_{left}'s fx={fx}, cy={p_left[1, 2]}",
            "a rectified pair sharing fx and cy",
        )
    baseline = (p_left[0, 3] - p_right[0, 3]) / fx
    if baseline <= 0:
        raise CalibrationError(
            path,
            f"P_rect_{right}",
            f"puts camera {right} {baseline:.4f} m right of {left}",
            f"camera {right} to the right of camera {left} (swap left/right)",
        )
    return from_rectified(
        fx, p_left[0, 2], p_left[1, 2], baseline, (int(width), int(height)), cx_right=p_right[0, 2], source=str(path)
    )
