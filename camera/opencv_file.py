"""OpenCV FileStorage calibration files (YAML, JSON or XML) with K1, D1, K2, D2, R, T.

Keys: `K1`, `K2` (3×3, px), `D1`, `D2` (OpenCV distortion vectors), `R` (3×3, left→right), `T`
(3, metres, left→right: `x_right = R @ x_left + T`), and the image size as `image_width` and
`image_height`. `M1`/`M2` (the names of OpenCV's stereo_calib sample) are read as `K1`/`K2`.
Optional `rectified: 1` marks an already rectified pair. Matrices may be stored as
`!!opencv-matrix` nodes or as plain (nested) number lists.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from camera.calibration import CalibrationError, StereoCalibration

#: Largest plausible baseline in metres; beyond this T was most likely written in millimetres.
MAX_BASELINE_M = 5.0

_ALIASES = {"K1": ("K1", "M1"), "K2": ("K2", "M2")}


def _open(path: Path) -> cv2.FileStorage:
    if not path.is_file():
        raise CalibrationError(path, "<file>", "does not exist", "an OpenCV YAML/JSON/XML calibration file")
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as error:  # OpenCV 5 surfaces parser errors as SystemError
        reason = getattr(error, "err", None) or getattr(error.__cause__, "err", None) or "parse error"
        raise CalibrationError(
            path, "<file>", f"is not a valid FileStorage file ({reason})", "OpenCV YAML, JSON or XML"
        ) from None
    if not storage.isOpened():
        raise CalibrationError(path, "<file>", "could not be opened by cv2.FileStorage", "OpenCV YAML, JSON or XML")
    return storage


#: Most numbers one calibration array holds (3×3 matrices, 14 distortion coefficients); a larger
#: matrix or list is refused before anything is allocated for it.
MAX_ARRAY_NUMBERS = 64
#: OpenCV's single-channel element types, as an `!!opencv-matrix` `dt` names them.
_MATRIX_TYPES = frozenset("ucwsifdh")
_MATRIX_FIELDS = ("rows", "cols", "dt", "data")
_MATRIX_EXPECTED = (
    f"an !!opencv-matrix with rows, cols, a one-letter dt and rows × cols ≤ {MAX_ARRAY_NUMBERS} data values"
)


def _number(node: cv2.FileNode, path: Path, key: str) -> float:
    """A number node's value; CalibrationError for anything else (text, map, nested list)."""
    if not (node.isInt() or node.isReal()):
        raise CalibrationError(path, key, "is not a matrix or a list of numbers", "numbers")
    return node.real()


def _sequence_values(node: cv2.FileNode, path: Path, key: str) -> list[float]:
    """The numbers of a list or a list of rows (`[[1, 2, 3], [4, 5, 6]]`), at most `MAX_ARRAY_NUMBERS`."""
    values: list[float] = []
    for i in range(node.size()):
        item = node.at(i)
        row = [item.at(j) for j in range(min(item.size(), MAX_ARRAY_NUMBERS + 1))] if item.isSeq() else [item]
        values.extend(_number(value, path, key) for value in row)
        if len(values) > MAX_ARRAY_NUMBERS:
            raise CalibrationError(
                path, key, f"holds more than {MAX_ARRAY_NUMBERS} numbers", "a calibration matrix or vector"
            )
    return values


def _matrix_values(node: cv2.FileNode, path: Path, key: str) -> list[float]:
    """The numbers of an `!!opencv-matrix` map, read field by field.

    OpenCV's own reader (`FileNode.mat()`) trusts rows, cols, dt and the data length: when they
    disagree (no `cols`, a multi-channel `dt`, too few values) it can corrupt the heap and abort
    the whole process, so it is never called; every field is checked here first.
    """
    fields = {name: node.getNode(name) for name in _MATRIX_FIELDS}
    if all(field.empty() for field in fields.values()):
        raise CalibrationError(path, key, "is not a matrix or a list of numbers", "numbers")
    missing = [name for name, field in fields.items() if field.empty()]
    if missing:
        raise CalibrationError(path, key, f"is a matrix without {', '.join(missing)}", _MATRIX_EXPECTED)
    shape = []
    for name in ("rows", "cols"):
        field = fields[name]
        if not field.isInt() or not 1 <= field.real() <= MAX_ARRAY_NUMBERS:
            raise CalibrationError(path, key, f"has {name} = {_text(field)}", _MATRIX_EXPECTED)
        shape.append(int(field.real()))
    rows, cols = shape
    dt = fields["dt"].string() if fields["dt"].isString() else _text(fields["dt"])
    if dt not in _MATRIX_TYPES:
        raise CalibrationError(path, key, f"has dt = {dt!r} (multi-channel or unknown)", _MATRIX_EXPECTED)
    data = fields["data"]
    count = data.size() if data.isSeq() else 0
    if rows * cols > MAX_ARRAY_NUMBERS or count != rows * cols:
        raise CalibrationError(path, key, f"has rows × cols = {rows}×{cols} but {count} data values", _MATRIX_EXPECTED)
    return [_number(data.at(i), path, key) for i in range(count)]


def _text(node: cv2.FileNode) -> str:
    """A scalar node as the file wrote it, for messages ('x', 3, 2.5); '<list>'/'<map>' otherwise."""
    if node.isString():
        return repr(node.string())
    if node.isInt() or node.isReal():
        return f"{node.real():g}"
    return "<list>" if node.isSeq() else "<map>"


def _read_array(storage: cv2.FileStorage, path: Path, key: str, size: int | None) -> np.ndarray:
    for name in _ALIASES.get(key, (key,)):
        node = storage.getNode(name)
        if not node.empty():
            break
    else:
        raise CalibrationError(path, key, "key is missing", f"a {'3×3 matrix' if size == 9 else 'number list'}")
    expected = f"{size} numbers" if size else "numbers"
    try:
        if node.isMap():
            numbers = _matrix_values(node, path, name)
        elif node.isSeq():
            numbers = _sequence_values(node, path, name)
        else:
            numbers = [_number(node, path, name)]
    except CalibrationError as error:
        raise CalibrationError(
            path, name, error.problem, expected if error.expected == "numbers" else error.expected
        ) from None
    values = np.array(numbers, dtype=np.float64)
    if values.size == 0 or (size is not None and values.size != size):
        raise CalibrationError(path, name, f"holds {values.size} numbers", expected)
    return values


def _read_int(storage: cv2.FileStorage, path: Path, key: str, default: int | None) -> int:
    node = storage.getNode(key)
    if node.empty():
        if default is None:
            raise CalibrationError(path, key, "key is missing", "the image size in pixels (image_width, image_height)")
        return default
    if not (node.isInt() or node.isReal()) or not np.isfinite(node.real()):
        raise CalibrationError(path, key, f"is {_text(node)}, not a finite number", "an integer")
    return int(round(node.real()))


def from_opencv_file(path: str | Path, size: tuple[int, int] | None = None) -> StereoCalibration:
    """Load an OpenCV FileStorage stereo calibration; `size` (w, h) is used when the file has none."""
    path = Path(path)
    storage = _open(path)
    try:
        k1 = _read_array(storage, path, "K1", 9).reshape(3, 3)
        d1 = _read_array(storage, path, "D1", None)
        k2 = _read_array(storage, path, "K2", 9).reshape(3, 3)
        d2 = _read_array(storage, path, "D2", None)
        r = _read_array(storage, path, "R", None)
        t = _read_array(storage, path, "T", 3)
        width = _read_int(storage, path, "image_width", None if size is None else size[0])
        height = _read_int(storage, path, "image_height", None if size is None else size[1])
        rectified = bool(_read_int(storage, path, "rectified", 0))
    finally:
        storage.release()
    if r.size == 3:  # a Rodrigues vector, as some tools write
        r = cv2.Rodrigues(r)[0]
    elif r.size != 9:
        raise CalibrationError(path, "R", f"holds {r.size} numbers", "a 3×3 rotation matrix or a Rodrigues 3-vector")
    baseline = float(np.linalg.norm(t))
    if baseline > MAX_BASELINE_M:
        raise CalibrationError(
            path,
            "T",
            f"has length {baseline:g}, implausible in metres",
            f"a translation in metres (under {MAX_BASELINE_M} m; was it written in mm?)",
        )
    return StereoCalibration(
        k1, d1, k2, d2, r.reshape(3, 3), t, (width, height), is_rectified=rectified, source=str(path)
    )


def write_opencv_file(calibration: StereoCalibration, path: str | Path) -> Path:
    """Write a calibration as an OpenCV FileStorage file (format from the suffix: .yaml/.yml/.json/.xml)."""
    path = Path(path)
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        for key in ("K1", "D1", "K2", "D2", "R"):
            value = getattr(calibration, key)
            storage.write(key, value if value.ndim == 2 else value.reshape(1, -1))
        storage.write("T", calibration.T.reshape(3, 1))
        storage.write("image_width", calibration.width)
        storage.write("image_height", calibration.height)
        storage.write("rectified", int(calibration.is_rectified))
    finally:
        storage.release()
    return path
