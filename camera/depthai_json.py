"""Luxonis OAK calibration, as `dai.CalibrationHandler.eepromToJsonFile` writes it (and `eepromToJson` returns).

Structure used (the rest of the file is ignored):
`cameraData`: a list of `[socket, {intrinsicMatrix (3×3), width, height, distortionCoeff (14,
OpenCV order), cameraType (0 perspective), extrinsics {rotationMatrix (3×3), translation {x, y, z},
toCameraSocket, lengthUnit}}]`. The extrinsics of camera S map a point from S's frame to
`toCameraSocket`'s: `p_to = R @ p_S + t`, `t` in centimetres unless `lengthUnit` says otherwise
(depthai's LengthUnit: 0 m, 1 cm, 2 mm). `stereoRectificationData.leftCameraSocket` /
`rightCameraSocket` name the default stereo pair.

Intrinsics are scaled to the requested size the way `CalibrationHandler.getCameraIntrinsics(...,
keepAspectRatio=True)` does: scale by the width ratio, then centre vertically (a crop or a pad).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from camera.calibration import CalibrationError, StereoCalibration

#: Socket names depthai uses (CameraBoardSocket), mapped to their numbers.
SOCKETS: dict[str, int] = {
    "CAM_A": 0,
    "RGB": 0,
    "CENTER": 0,
    "A": 0,
    "CAM_B": 1,
    "LEFT": 1,
    "B": 1,
    "CAM_C": 2,
    "RIGHT": 2,
    "C": 2,
    "CAM_D": 3,
    "D": 3,
    "CAM_E": 4,
    "E": 4,
    "CAM_F": 5,
    "F": 5,
}

#: Metres per unit of depthai's LengthUnit values (METER, CENTIMETER, MILLIMETER, INCH, FOOT).
LENGTH_UNITS_M: dict[int, float] = {0: 1.0, 1: 0.01, 2: 0.001, 3: 0.0254, 4: 0.3048}
DEFAULT_LENGTH_UNIT = 1  # files written before lengthUnit existed hold centimetres


def socket_number(socket: int | str) -> int:
    """The board socket number for a socket given as a number or a name (CAM_B, LEFT, "1" …)."""
    if isinstance(socket, int):
        return socket
    text = str(socket).strip().upper().removeprefix("CAMERABOARDSOCKET.")
    if text.lstrip("-").isdigit():
        return int(text)
    if text not in SOCKETS:
        raise ValueError(f"unknown camera socket {socket!r}; expected a number or one of {', '.join(SOCKETS)}")
    return SOCKETS[text]


def integer_field(value: Any, source: str, key: str, expected: str) -> int:
    """An integer from a JSON field (socket numbers, enums), or a CalibrationError naming the key."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise CalibrationError(source, key, f"is {value!r}", expected)
    try:
        number = float(value)
    except ValueError:
        raise CalibrationError(source, key, f"is {value!r}", expected) from None
    if not number.is_integer():
        raise CalibrationError(source, key, f"is {value!r}", expected)
    return int(number)


def scale_intrinsics(matrix: np.ndarray, calib_size: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """A 3×3 pinhole matrix at `calib_size` (w, h) moved to `size` (w, h): width-ratio scale, centred vertically."""
    scale = size[0] / calib_size[0]
    scaled = np.array(matrix, dtype=np.float64)
    scaled[:2, :] *= scale
    scaled[2, :] = (0.0, 0.0, 1.0)
    scaled[1, 2] += (size[1] - calib_size[1] * scale) / 2.0
    return scaled


class _Cameras:
    """The cameraData entries of one file, with errors that name the file and the key."""

    def __init__(self, data: Any, source: str) -> None:
        self.source = source
        if not isinstance(data, dict) or not isinstance(data.get("cameraData"), list):
            raise CalibrationError(source, "cameraData", "is missing", "a depthai calibration JSON (eepromToJsonFile)")
        self.entries: dict[int, dict[str, Any]] = {}
        for index, item in enumerate(data["cameraData"]):
            if not (isinstance(item, list) and len(item) == 2 and isinstance(item[1], dict)):
                raise CalibrationError(
                    source, f"cameraData[{index}]", f"is {str(item)[:60]}", "a [socket, {intrinsicMatrix, …}] pair"
                )
            self.entries[integer_field(item[0], source, f"cameraData[{index}][0]", "a socket number")] = item[1]

    def entry(self, socket: int) -> dict[str, Any]:
        """The cameraData entry of a socket, or a CalibrationError listing the file's sockets."""
        if socket not in self.entries:
            raise CalibrationError(
                self.source,
                f"cameraData socket {socket}",
                "is missing",
                f"one of the file's sockets {sorted(self.entries)}",
            )
        return self.entries[socket]

    def array(self, socket: int, key: str, shape: tuple[int, ...], where: str = "") -> np.ndarray:
        """A finite numeric array of `shape` from the socket's entry (or its `where` sub-dict)."""
        container = self.entry(socket)
        if where:
            container = container.get(where) or {}
        label = f"cameraData[{socket}].{where + '.' if where else ''}{key}"
        try:
            values = np.array(container[key], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            raise CalibrationError(
                self.source, label, "is missing or not numeric", f"numbers of shape {shape}"
            ) from None
        if values.shape != shape:
            raise CalibrationError(self.source, label, f"has shape {values.shape}", f"shape {shape}")
        if not np.all(np.isfinite(values)):
            raise CalibrationError(self.source, label, "contains a non-finite value", "finite numbers")
        return values

    def intrinsics(self, socket: int, size: tuple[int, int] | None) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """(K scaled to `size` (3×3 px), distortion (n,), size (w, h)); `size` None keeps the calibration size."""
        entry = self.entry(socket)
        camera_type = integer_field(
            entry.get("cameraType", 0), self.source, f"cameraData[{socket}].cameraType", "0 (perspective)"
        )
        if camera_type != 0:
            raise CalibrationError(
                self.source,
                f"cameraData[{socket}].cameraType",
                f"is {entry['cameraType']}",
                "0 (perspective); fisheye and other models are not supported",
            )
        matrix = self.array(socket, "intrinsicMatrix", (3, 3))
        try:
            calib_size = (int(entry["width"]), int(entry["height"]))
        except (KeyError, TypeError, ValueError):
            raise CalibrationError(
                self.source, f"cameraData[{socket}].width/height", "is missing", "the calibration image size in pixels"
            ) from None
        if min(calib_size) <= 0:
            raise CalibrationError(
                self.source,
                f"cameraData[{socket}].width/height",
                f"is {calib_size}",
                "a positive calibration image size in pixels",
            )
        raw_coeffs = entry.get("distortionCoeff") or [0.0] * 14
        label = f"cameraData[{socket}].distortionCoeff"
        try:
            coeffs = np.array(raw_coeffs, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise CalibrationError(
                self.source, label, f"is {str(raw_coeffs)[:60]}", "a list of 14 OpenCV distortion coefficients"
            ) from None
        if coeffs.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(coeffs)):
            raise CalibrationError(
                self.source, label, f"has {coeffs.size} values", "14 finite OpenCV distortion coefficients"
            )
        out_size = calib_size if size is None else (int(size[0]), int(size[1]))
        return scale_intrinsics(matrix, calib_size, out_size), coeffs, out_size

    def to_root(self, socket: int) -> tuple[np.ndarray, int]:
        """The 4×4 transform (metres) from `socket`'s frame to the end of its extrinsics chain, and that end."""
        transform = np.eye(4)
        seen = [socket]
        current = socket
        while True:
            extrinsics = self.entry(current).get("extrinsics") or {}
            target = integer_field(
                extrinsics.get("toCameraSocket", -1),
                self.source,
                f"cameraData[{current}].extrinsics.toCameraSocket",
                "a socket number (-1: none)",
            )
            if target < 0:
                return transform, current
            if target in seen:
                raise CalibrationError(
                    self.source,
                    f"cameraData[{current}].extrinsics.toCameraSocket",
                    f"loops back to socket {target} ({' → '.join(map(str, seen + [target]))})",
                    "a chain of extrinsics without cycles",
                )
            rotation = self.array(current, "rotationMatrix", (3, 3), "extrinsics")
            translation = extrinsics.get("translation") or {}
            try:
                t = np.array([translation[k] for k in "xyz"], dtype=np.float64)
            except (KeyError, TypeError, ValueError):
                raise CalibrationError(
                    self.source,
                    f"cameraData[{current}].extrinsics.translation",
                    "is missing or incomplete",
                    "{x, y, z} in centimetres",
                ) from None
            unit = integer_field(
                extrinsics.get("lengthUnit", DEFAULT_LENGTH_UNIT),
                self.source,
                f"cameraData[{current}].extrinsics.lengthUnit",
                f"one of {sorted(LENGTH_UNITS_M)}",
            )
            if unit not in LENGTH_UNITS_M:
                raise CalibrationError(
                    self.source,
                    f"cameraData[{current}].extrinsics.lengthUnit",
                    f"is {unit}",
                    f"one of {sorted(LENGTH_UNITS_M)} (m, cm, mm, inch, foot)",
                )
            step = np.eye(4)
            step[:3, :3] = rotation
            step[:3, 3] = t * LENGTH_UNITS_M[unit]
            transform = step @ transform
            seen.append(target)
            current = target


def _chosen_socket(data: dict[str, Any], source: str, chosen: int | str | None, key: str, fallback: int) -> int:
    """The socket asked for, else the file's stereo pair entry `key`, else `fallback`."""
    if chosen is not None:
        try:
            return socket_number(chosen)
        except ValueError as error:
            raise CalibrationError(source, key, str(error), "a depthai camera socket") from None
    section = data.get("stereoRectificationData")
    value = section.get(key) if isinstance(section, dict) else None
    if value is None:
        return fallback
    number = integer_field(value, source, f"stereoRectificationData.{key}", "a socket number")
    return fallback if number < 0 else number


def calibrated_size(data: Any, socket: int | str, source: str) -> tuple[int, int]:
    """(width, height) in pixels at which `socket`'s camera in a parsed depthai calibration was calibrated."""
    try:
        number = socket_number(socket)
    except ValueError as error:
        raise CalibrationError(source, "socket", str(error), "a depthai camera socket") from None
    return _Cameras(data, source).intrinsics(number, None)[2]


def calibration_from_depthai_dict(
    data: Any,
    source: str,
    left_socket: int | str | None = None,
    right_socket: int | str | None = None,
    size: tuple[int, int] | None = None,
) -> StereoCalibration:
    """A stereo calibration from depthai's calibration JSON already parsed into a dict (see module doc)."""
    cameras = _Cameras(data, source)
    left = _chosen_socket(data, source, left_socket, "leftCameraSocket", 1)
    right = _chosen_socket(data, source, right_socket, "rightCameraSocket", 2)
    k1, d1, out_size = cameras.intrinsics(left, size)
    k2, d2, _ = cameras.intrinsics(right, out_size)
    left_to_root, left_root = cameras.to_root(left)
    right_to_root, right_root = cameras.to_root(right)
    if left_root != right_root:
        raise CalibrationError(
            source,
            f"cameraData[{left}].extrinsics",
            f"sockets {left} and {right} are not linked (chains end at {left_root} and {right_root})",
            "extrinsics that connect the two cameras",
        )
    left_to_right = np.linalg.inv(right_to_root) @ left_to_root
    return StereoCalibration(k1, d1, k2, d2, left_to_right[:3, :3], left_to_right[:3, 3], out_size, source=source)


def from_depthai_json(
    path: str | Path,
    left_socket: int | str | None = None,
    right_socket: int | str | None = None,
    size: tuple[int, int] | None = None,
) -> StereoCalibration:
    """Load an OAK calibration JSON for a socket pair (default: the file's stereo pair, else CAM_B/CAM_C).

    `size` (w, h) is the frame size the cameras will deliver; intrinsics are scaled to it
    (default: the left camera's calibration size).
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except OSError as error:
        raise CalibrationError(
            path, "<file>", f"cannot be read ({error.strerror})", "a depthai calibration JSON"
        ) from None
    except json.JSONDecodeError as error:
        raise CalibrationError(
            path, f"line {error.lineno}", f"is not valid JSON ({error.msg})", "a depthai calibration JSON"
        ) from None
    return calibration_from_depthai_dict(data, str(path), left_socket, right_socket, size)
