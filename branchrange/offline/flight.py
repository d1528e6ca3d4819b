"""The truth of a flight recording: `flight.json` beside `recording.json` (written by `branchrange synth-flight`).

```
{"format": "branchrange-flight", "version": 1,
 "poses": [{"index": 0, "timestamp_ns": 1000000000, "R_world_cam": [[…], […], […]], "t_world_cam": [x, y, z],
            "visible_cut_ids": [1, 3]}, …],
 "cut_points": [{"id": 1, "world_m": [x, y, z], "radius_m": 0.012}, …]}
```
World frame = the rectified left camera frame of the first frame (OpenCV axes: x right, y down,
z forward; metres); a pose maps camera to world: `X_world = R_world_cam · X_cam + t_world_cam`.
Poses are listed in recording order (position p = row p of timestamps.csv); `index` and
`timestamp_ns` repeat the recording's. `visible_cut_ids` (our addition to the issue's format;
optional when reading, None when absent) lists the cut points that frame shows: in front of the
camera, inside the image, and the mask at its pixel is its branch. Cut point ids are the branches'
mask ids.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

FLIGHT_NAME = "flight.json"
FORMAT_NAME = "branchrange-flight"
FORMAT_VERSION = 1
#: Largest |Rᵀ·R − I| entry accepted for a rotation read from a file.
ROTATION_TOLERANCE = 1e-6


class FlightFormatError(ValueError):
    """flight.json is missing, unreadable or breaks the format; the message names the file and key."""


@dataclass(frozen=True, eq=False)
class FlightPose:
    """The left camera's pose at one frame: `R_world_cam` float64 `(3, 3)`, `t_world_cam` float64 `(3,)` m."""

    index: int
    timestamp_ns: int
    R_world_cam: np.ndarray
    t_world_cam: np.ndarray
    visible_cut_ids: list[int] | None = None


@dataclass(frozen=True, eq=False)
class FlightCutPoint:
    """A true cut point: its branch's mask id, position `world_m` float64 `(3,)` m, branch radius there (m)."""

    id: int
    world_m: np.ndarray
    radius_m: float


def _fail(path: Path, key: str, found: object, expected: str) -> FlightFormatError:
    shown = repr(found)
    return FlightFormatError(
        f"{path}: {key} is {shown if len(shown) <= 80 else shown[:77] + '...'}; expected {expected}"
    )


def _integer(value: Any, path: Path, key: str, minimum: int = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise _fail(path, key, value, f"an integer ≥ {minimum}")
    return value


def _numbers(value: Any, shape: tuple[int, ...], path: Path, key: str) -> np.ndarray:
    """`value` as a finite float64 array of `shape`, else FlightFormatError."""
    expected = f"{'×'.join(map(str, shape))} finite numbers"
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail(path, key, value, expected) from None
    if array.shape != shape or not np.all(np.isfinite(array)) or _has_bool(value):
        raise _fail(path, key, value, expected)
    return array


def _has_bool(value: Any) -> bool:
    return isinstance(value, bool) or (isinstance(value, list) and any(_has_bool(v) for v in value))


def _entries(document: dict[str, Any], key: str, path: Path) -> list[dict[str, Any]]:
    entries = document.get(key)
    if not isinstance(entries, list) or not all(isinstance(entry, dict) for entry in entries):
        raise _fail(path, key, entries, "a list of objects")
    return entries


def _field(entry: dict[str, Any], name: str, path: Path, key: str) -> Any:
    if name not in entry:
        raise FlightFormatError(f"{path}: {key} has no {name!r}; expected keys {sorted(entry) + [name]}")
    return entry[name]


def _read_pose(entry: dict[str, Any], path: Path, key: str) -> FlightPose:
    rotation = _numbers(_field(entry, "R_world_cam", path, key), (3, 3), path, f"{key}.R_world_cam")
    if np.abs(rotation.T @ rotation - np.eye(3)).max() > ROTATION_TOLERANCE or np.linalg.det(rotation) <= 0:
        raise _fail(path, f"{key}.R_world_cam", rotation.tolist(), "a rotation matrix (orthonormal, determinant +1)")
    translation = _numbers(_field(entry, "t_world_cam", path, key), (3,), path, f"{key}.t_world_cam")
    visible = entry.get("visible_cut_ids")
    if visible is not None:
        if not isinstance(visible, list):
            raise _fail(path, f"{key}.visible_cut_ids", visible, "a list of cut point ids")
        visible = [_integer(v, path, f"{key}.visible_cut_ids", 1) for v in visible]
    return FlightPose(
        _integer(_field(entry, "index", path, key), path, f"{key}.index"),
        _integer(_field(entry, "timestamp_ns", path, key), path, f"{key}.timestamp_ns"),
        rotation,
        translation,
        visible,
    )


def _read_cut(entry: dict[str, Any], path: Path, key: str) -> FlightCutPoint:
    radius = _field(entry, "radius_m", path, key)
    if isinstance(radius, bool) or not isinstance(radius, (int, float)) or not (math.isfinite(radius) and radius > 0):
        raise _fail(path, f"{key}.radius_m", radius, "a branch radius > 0 m")
    return FlightCutPoint(
        _integer(_field(entry, "id", path, key), path, f"{key}.id", 1),
        _numbers(_field(entry, "world_m", path, key), (3,), path, f"{key}.world_m"),
        float(radius),
    )


def _inconsistency(poses: list[FlightPose], cuts: list[FlightCutPoint]) -> str | None:
    """What makes poses and cut points disagree (times not increasing, ids repeated or unknown), or None."""
    stamps = [pose.timestamp_ns for pose in poses]
    if any(b <= a for a, b in zip(stamps, stamps[1:])):
        return f"poses[].timestamp_ns are {stamps[:6]}…; expected increasing capture times"
    ids = [cut.id for cut in cuts]
    if len(set(ids)) != len(ids):
        return f"cut_points[].id are {ids}; expected distinct ids"
    for position, pose in enumerate(poses):
        unknown = sorted(set(pose.visible_cut_ids or ()) - set(ids))
        if unknown:
            return f"poses[{position}].visible_cut_ids names {unknown}; expected ids of cut_points {ids}"
    return None


@dataclass(frozen=True, eq=False)
class FlightTruth:
    """Camera poses and true cut points of a flight recording (see the module docstring)."""

    poses: list[FlightPose]
    cut_points: list[FlightCutPoint]

    def __post_init__(self) -> None:
        problem = _inconsistency(self.poses, self.cut_points)
        if problem:
            raise FlightFormatError(f"{FLIGHT_NAME}: {problem}")

    @classmethod
    def load(cls, directory: str | Path) -> FlightTruth:
        """Read `directory/flight.json`; FlightFormatError names the file and the key at fault."""
        path = Path(directory) / FLIGHT_NAME
        try:
            document = json.loads(path.read_text(encoding="utf-8"))
        except OSError as error:
            raise FlightFormatError(
                f"{path}: cannot be read ({error.strerror}); expected the flight truth "
                "`branchrange synth-flight` writes beside recording.json"
            ) from None
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise FlightFormatError(f"{path}: is not JSON ({error}); expected a {FORMAT_NAME} document") from None
        if not isinstance(document, dict) or document.get("format") != FORMAT_NAME:
            found = document.get("format") if isinstance(document, dict) else document
            raise _fail(path, "format", found, repr(FORMAT_NAME))
        if document.get("version") != FORMAT_VERSION:
            raise _fail(path, "version", document.get("version"), str(FORMAT_VERSION))
        poses = [_read_pose(entry, path, f"poses[{i}]") for i, entry in enumerate(_entries(document, "poses", path))]
        cuts = [
            _read_cut(entry, path, f"cut_points[{i}]") for i, entry in enumerate(_entries(document, "cut_points", path))
        ]
        problem = _inconsistency(poses, cuts)
        if problem:
            raise FlightFormatError(f"{path}: {problem}")
        return cls(poses, cuts)

    def write(self, directory: str | Path) -> Path:
        """Write `directory/flight.json` (the directory must exist); returns its path."""
        poses = [
            {
                "index": pose.index,
                "timestamp_ns": pose.timestamp_ns,
                "R_world_cam": np.asarray(pose.R_world_cam, dtype=np.float64).tolist(),
                "t_world_cam": np.asarray(pose.t_world_cam, dtype=np.float64).tolist(),
                **({} if pose.visible_cut_ids is None else {"visible_cut_ids": list(pose.visible_cut_ids)}),
            }
            for pose in self.poses
        ]
        cuts = [
            {
                "id": cut.id,
                "world_m": np.asarray(cut.world_m, dtype=np.float64).tolist(),
                "radius_m": float(cut.radius_m),
            }
            for cut in self.cut_points
        ]

        def listing(entries: list[dict[str, Any]]) -> str:
            """A JSON list with one entry per line (floats keep every digit, so reading gives them back exactly)."""
            return "[" + ",".join(f"\n  {json.dumps(entry)}" for entry in entries) + ("\n ]" if entries else "]")

        text = (
            f'{{"format": "{FORMAT_NAME}", "version": {FORMAT_VERSION},\n'
            f' "poses": {listing(poses)},\n "cut_points": {listing(cuts)}}}\n'
        )
        path = Path(directory) / FLIGHT_NAME
        path.write_text(text, encoding="utf-8")
        return path

    def cut_points_in_camera(self, position: int) -> dict[int, np.ndarray]:
        """Cut point id → its position `(3,)` m in the left camera frame of the frame at `position` (0-based)."""
        if not 0 <= position < len(self.poses):
            raise IndexError(f"frame position {position} is outside the flight's 0..{len(self.poses) - 1}")
        pose = self.poses[position]
        return {cut.id: pose.R_world_cam.T @ (cut.world_m - pose.t_world_cam) for cut in self.cut_points}

    def pose_at(self, timestamp_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """(R_world_cam `(3, 3)`, t_world_cam `(3,)` m) at `timestamp_ns`, between the recorded poses.

        Rotation by spherical interpolation (constant angular rate about one axis), translation
        linearly. ValueError outside the first..last timestamps: the truth is not extrapolated.
        """
        stamps = [pose.timestamp_ns for pose in self.poses]
        if not stamps or not stamps[0] <= timestamp_ns <= stamps[-1]:
            span = f"{stamps[0]}..{stamps[-1]} ns" if stamps else "no poses"
            raise ValueError(f"timestamp {timestamp_ns} ns is outside the flight ({span}); no extrapolation")
        after = int(np.searchsorted(stamps, timestamp_ns, side="left"))
        if stamps[after] == timestamp_ns:
            pose = self.poses[after]
            return pose.R_world_cam.copy(), pose.t_world_cam.copy()
        a, b = self.poses[after - 1], self.poses[after]
        fraction = (timestamp_ns - a.timestamp_ns) / (b.timestamp_ns - a.timestamp_ns)
        turn, _ = cv2.Rodrigues(a.R_world_cam.T @ b.R_world_cam)
        partial, _ = cv2.Rodrigues(fraction * turn)
        return a.R_world_cam @ partial, (1 - fraction) * a.t_world_cam + fraction * b.t_world_cam
