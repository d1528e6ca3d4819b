"""`load_calibration`: open any supported calibration file, recognised by its content, not its name."""

from __future__ import annotations

import dataclasses
import json
import tempfile
from pathlib import Path

from camera.calibration import CalibrationError, StereoCalibration, read_calibration_text
from camera.depthai_json import calibration_from_depthai_dict
from camera.kitti import from_kitti
from camera.middlebury import from_middlebury_calib
from camera.opencv_file import from_opencv_file
from camera.zed_conf import from_zed_conf

#: File suffix of each format, for uploads written to a temporary file (the content decides).
_SUFFIXES = {"zed": ".conf", "depthai": ".json", "kitti": ".txt", "middlebury": ".txt"}


def detect_format(path: str | Path) -> str:
    """Which calibration format a file holds: "zed", "opencv", "depthai", "kitti" or "middlebury"."""
    return _format_of_text(read_calibration_text(path), path)


def _format_of_text(text: str, path: str | Path) -> str:
    """`detect_format` on a file's text; `path` names the file in the error."""
    head = text.lstrip()
    if head.startswith("{"):
        try:
            data = json.loads(head)
        except json.JSONDecodeError:
            data = None
        if isinstance(data, dict) and "cameraData" in data:
            return "depthai"
        return "opencv"
    if head.startswith("%YAML") or head.startswith("<?xml") or "<opencv_storage>" in head[:200]:
        return "opencv"
    lines = {line.split("=")[0].split(":")[0].strip().upper() for line in text.splitlines()}
    if any(line.startswith("[LEFT_CAM_") for line in lines) or "[STEREO]" in lines:
        return "zed"
    if any(line.startswith("P_RECT_") for line in lines):
        return "kitti"
    if {"K1", "M1"} & lines:
        return "opencv"
    if {"CAM0", "CAM1", "BASELINE"} <= lines:
        return "middlebury"
    raise CalibrationError(
        path,
        "<file>",
        "is in no known calibration format",
        "a ZED SN*.conf, an OpenCV YAML/JSON/XML with K1 D1 K2 D2 R T, "
        "a depthai calibration JSON, a KITTI calib_cam_to_cam.txt or a Middlebury calib.txt",
    )


def load_calibration(
    path: str | Path,
    resolution: str | None = None,
    *,
    size: tuple[int, int] | None = None,
    left_socket: int | str | None = None,
    right_socket: int | str | None = None,
    kitti_left: str = "02",
    kitti_right: str = "03",
) -> StereoCalibration:
    """Load a stereo calibration of any supported format.

    `resolution` picks a ZED file's resolution (2K/FHD/HD/VGA; required for ZED files). `size`
    (w, h) is the frame size for depthai files (intrinsics are scaled to it) and the image size of
    OpenCV files that do not store one. `left_socket`/`right_socket` pick depthai cameras,
    `kitti_left`/`kitti_right` KITTI cameras.
    """
    fmt = detect_format(path)
    if fmt == "zed":
        if resolution is None:
            raise CalibrationError(
                path, "resolution", "was not given for a ZED calibration file", "resolution= one of 2K, FHD, HD, VGA"
            )
        return from_zed_conf(path, resolution)
    if fmt == "depthai":
        data = json.loads(read_calibration_text(path))
        return calibration_from_depthai_dict(data, str(path), left_socket, right_socket, size)
    if fmt == "kitti":
        return from_kitti(path, kitti_left, kitti_right)
    if fmt == "middlebury":
        return from_middlebury_calib(path)
    return from_opencv_file(path, size)


def _upload_suffix(data: bytes) -> str:
    """The suffix a calibration of this content is saved under: by format, and for OpenCV by syntax."""
    text = data.decode("utf-8-sig", errors="replace").lstrip()
    try:
        fmt = _format_of_text(text, "<upload>")
    except CalibrationError:
        return ".txt"
    if fmt == "opencv":
        return ".json" if text.startswith("{") else ".xml" if text.startswith("<") else ".yaml"
    return _SUFFIXES[fmt]


def load_calibration_bytes(
    data: bytes, name: str, resolution: str | None = None, *, size: tuple[int, int] | None = None
) -> StereoCalibration:
    """`load_calibration` of a file's bytes (an upload), with errors naming it `name`.

    The bytes go to a private temporary folder under a fixed name whose suffix the content
    chooses, never under a name the sender chose (`..`, a NUL byte or 300 characters would make
    the write itself fail, or escape the folder).
    """
    with tempfile.TemporaryDirectory(prefix="calibration-") as folder:
        path = Path(folder) / f"calibration{_upload_suffix(data)}"
        path.write_bytes(data)
        try:
            return dataclasses.replace(load_calibration(path, resolution, size=size), source=name)
        except CalibrationError as error:
            raise CalibrationError(name, error.key, error.problem.replace(str(path), name), error.expected) from None
        except ValueError as error:
            raise ValueError(str(error).replace(str(path), name)) from None
