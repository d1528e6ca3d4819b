"""Stereolabs ZED factory calibration files (`SN<serial>.conf`), as the ZED SDK downloads them.

INI sections `[LEFT_CAM_<RES>]`, `[RIGHT_CAM_<RES>]` (RES: 2K, FHD, HD, VGA) with `fx fy cx cy k1 k2
[p1 p2 k3]` in pixels at that resolution, and `[STEREO]` with `Baseline` (or `BaseLine`) in mm,
`TY`/`TZ` (or per-resolution `TY_<RES>`/`TZ_<RES>`, preferred) in mm and `RX_<RES>`, `CV_<RES>`,
`RZ_<RES>`: a Rodrigues rotation vector [RX, CV, RZ] in radians.

Files in the wild carry a UTF-8 byte-order mark, CRLF line endings, either spelling of Baseline and
no p1/p2/k3 (taken as 0, as the ZED SDK does). Section and key names are case-insensitive.

Geometry: as in Stereolabs' own OpenCV rectification sample (`initCalibration` in
zed-open-capture's examples/include/calibration.hpp, the same in zed-opencv-native),
`R = Rodrigues([RX, CV, RZ])` is used as OpenCV's left→right rotation and the translation lies
along [Baseline, TY_<RES>, TZ_<RES>]. The sample passes that translation with a positive sign; we
store it with OpenCV's, `T = -[Baseline, TY, TZ] / 1000` metres (as rtabmap's ZED Open Capture
driver does), so that the rectified right projection has `P2[0,3] < 0`, `|P2[0,3] / P2[0,0]|` is the
baseline and disparities of points in front are positive. stereoRectify rotates T onto ±x by the
same rotation whatever its sign, so R1, R2, P1 and the maps are exactly the sample's
(tests/test_camera_rectify.py pins this on the real files). Not verified on real images: that the
Rodrigues vector is left→right and not its inverse. Reading it the other way round would leave
rows 5–13 px apart at HD on the shared files (see camera/README.md for the check to run on a camera).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from camera.calibration import CalibrationError, StereoCalibration, camera_matrix, parse_number, read_calibration_text

#: Image size (width, height) of one eye at each resolution of the file.
ZED_RESOLUTIONS: dict[str, tuple[int, int]] = {
    "2K": (2208, 1242),
    "FHD": (1920, 1080),
    "HD": (1280, 720),
    "VGA": (672, 376),
}

#: Other names users give the resolutions (ZED SDK mode names), mapped to the file's names.
RESOLUTION_ALIASES: dict[str, str] = {"HD2K": "2K", "HD1080": "FHD", "1080": "FHD", "HD720": "HD", "720": "HD"}


def resolution_name(resolution: str) -> str:
    """The file's name ("2K", "FHD", "HD", "VGA") for a resolution or ZED mode name, any case."""
    name = resolution.strip().upper()
    name = RESOLUTION_ALIASES.get(name, name)
    if name not in ZED_RESOLUTIONS:
        raise ValueError(
            f"unknown ZED resolution {resolution!r}; expected one of "
            f"{', '.join(ZED_RESOLUTIONS)} (or {', '.join(RESOLUTION_ALIASES)})"
        )
    return name


def resolution_for_size(size: tuple[int, int]) -> str | None:
    """The file's resolution name for one eye's (width, height) in pixels, None when no ZED resolution has it."""
    for name, resolution_size in ZED_RESOLUTIONS.items():
        if tuple(size) == resolution_size:
            return name
    return None


def parse_ini(text: str, source: str | Path) -> dict[str, dict[str, str]]:
    """Sections of an INI text as {SECTION: {key: value}}, section names upper-case, keys lower-case."""
    sections: dict[str, dict[str, str]] = {}
    current: dict[str, str] | None = None
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line[0] in ";#":
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1].strip().upper(), {})
            continue
        key, sep, value = line.partition("=")
        if not sep or current is None:
            raise CalibrationError(
                source, f"line {number}", f"reads {raw!r}", "'[SECTION]' or 'key=value' inside a section"
            )
        current[key.strip().lower()] = value.strip()
    return sections


def _section(sections: dict[str, dict[str, str]], name: str, source: Path) -> dict[str, str]:
    if name not in sections:
        available = sorted(sections) or ["none"]
        raise CalibrationError(
            source, f"[{name}]", "section is missing", f"a [{name}] section (file has {', '.join(available)})"
        )
    return sections[name]


def _value(
    section: dict[str, str],
    keys: tuple[str, ...],
    where: str,
    source: Path,
    default: float | None = None,
    unit: str = "",
) -> float:
    """The first of `keys` present in the section, as a number; `default` when none is and one is given."""
    for key in keys:
        if key in section:
            return parse_number(source, f"{where} {key}", section[key])
    if default is not None:
        return default
    raise CalibrationError(source, f"{where} {' or '.join(keys)}", "key is missing", f"a number{unit}")


def _intrinsics(sections: dict[str, dict[str, str]], eye: str, res: str, source: Path) -> tuple[np.ndarray, np.ndarray]:
    name = f"{eye}_CAM_{res}"
    section = _section(sections, name, source)
    where = f"[{name}]"
    fx, fy, cx, cy = (_value(section, (key,), where, source, unit=" in pixels") for key in ("fx", "fy", "cx", "cy"))
    k1, k2, p1, p2, k3 = (_value(section, (key,), where, source, default=0.0) for key in ("k1", "k2", "p1", "p2", "k3"))
    return camera_matrix(fx, fy, cx, cy), np.array([k1, k2, p1, p2, k3])


def available_resolutions(path: str | Path) -> list[str]:
    """The resolutions a ZED calibration file has both eyes for."""
    sections = parse_ini(read_calibration_text(path), path)
    return [res for res in ZED_RESOLUTIONS if f"LEFT_CAM_{res}" in sections and f"RIGHT_CAM_{res}" in sections]


def from_zed_conf(path: str | Path, resolution: str) -> StereoCalibration:
    """Load a ZED `SN<serial>.conf` at one resolution (2K/FHD/HD/VGA or HD2K/HD1080/HD720).

    Returns raw intrinsics at that resolution, `R` from the Rodrigues vector [RX, CV, RZ] and
    `T` in metres with OpenCV's sign (see the module docstring).
    """
    path = Path(path)
    sections = parse_ini(read_calibration_text(path), path)
    try:
        res = resolution_name(resolution)
    except ValueError as error:
        raise CalibrationError(path, "resolution", str(error), "2K, FHD, HD or VGA") from None
    if f"LEFT_CAM_{res}" not in sections:
        have = available_resolutions(path)
        raise CalibrationError(
            path,
            f"[LEFT_CAM_{res}]",
            f"resolution {res} is not in the file",
            f"one of the file's resolutions: {', '.join(have) or 'none'}",
        )
    k1, d1 = _intrinsics(sections, "LEFT", res, path)
    k2, d2 = _intrinsics(sections, "RIGHT", res, path)
    stereo = _section(sections, "STEREO", path)
    baseline_mm = _value(stereo, ("baseline",), "[STEREO]", path, unit=" (baseline in mm)")
    if baseline_mm <= 0:
        raise CalibrationError(path, "[STEREO] Baseline", f"is {baseline_mm}", "a positive baseline in mm")
    res_l = res.lower()
    ty = _value(stereo, (f"ty_{res_l}", "ty"), "[STEREO]", path, default=0.0)
    tz = _value(stereo, (f"tz_{res_l}", "tz"), "[STEREO]", path, default=0.0)
    rotation = [
        _value(stereo, (f"{axis}_{res_l}", axis), "[STEREO]", path, unit=" in radians") for axis in ("rx", "cv", "rz")
    ]
    rmat, _ = cv2.Rodrigues(np.array(rotation, dtype=np.float64))
    t = -np.array([baseline_mm, ty, tz]) / 1000.0
    return StereoCalibration(k1, d1, k2, d2, rmat, t, ZED_RESOLUTIONS[res], source=str(path))
