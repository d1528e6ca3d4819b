"""The per-frame result, typed: what `Pipeline` returns and every consumer reads (`branchrange/v1`).

`FrameResult` and its parts are frozen dataclasses; consumers read attributes, and the branch to
approach is `result.target` (worked out here only). Dicts appear only at the edges:
`to_json_dict()` gives the `branchrange/v1` JSON object (JSONL logs, HTTP, `--json`) and
`FrameResult.from_json_dict()` reads a logged line back (validated, `ResultFormatError` naming the key).
The JSON schema (`json_schema()`, packaged as `branchrange/core/schemas/result_v1.json`) and the API's
response model are generated from these classes, so the format is written down once.

Units: metres, pixels of the rectified left image, milliseconds; 3D vectors in the rectified left
camera frame (OpenCV axes: x right, y down, z forward). Optional parts that are None are left out of
the JSON (as the pipeline always did); required ones that may be None (`target_id`,
`pair_check.median_dy_px`, `targets.target_track_id`) are written as null.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Final, Literal

from pydantic import ConfigDict, Field, TypeAdapter, ValidationError, with_config

from branchrange.core.geometry import StereoGeometry

if TYPE_CHECKING:
    from branchrange.core.cutpoints import BranchEstimate, DroppedBranch
    from branchrange.core.light_check import LightReading
    from branchrange.core.pair_check import PairCheck
    from branchrange.core.roi import Region
    from branchrange.core.segmentation.ood import OodReading

SCHEMA_ID: Final = "branchrange/v1"
#: The schema generated from these classes (`json_schema`), kept in the package for other languages' readers.
SCHEMA_PATH = Path(__file__).with_name("schemas") / "result_v1.json"

NonNegInt = Annotated[int, Field(ge=0)]
NonNegFloat = Annotated[float, Field(ge=0)]
Fraction = Annotated[float, Field(ge=0, le=1)]
Vector3 = tuple[float, float, float]
_STRICT = ConfigDict(extra="forbid")


class JsonPart:
    """A part of the result that writes itself as its `branchrange/v1` JSON object."""

    def to_json_dict(self) -> dict[str, Any]:
        """The JSON object: keys in field order, None-valued optional parts left out, tuples as lists."""
        as_json: dict[str, Any] = _to_json(self)
        return as_json


class ResultFormatError(ValueError):
    """A JSON object that is not a `branchrange/v1` result; the message names the key and what was wrong."""


@with_config(_STRICT)
@dataclass(frozen=True)
class Frame(JsonPart):
    """Which frame the result is of."""

    index: Annotated[int, Field(ge=0, description="frame number (0 for single pairs)")]
    timestamp_ns: Annotated[int, Field(ge=0, description="monotonic capture time, nanoseconds")]
    width: Annotated[int, Field(ge=1, description="pixels")]
    height: Annotated[int, Field(ge=1, description="pixels")]


@with_config(_STRICT)
@dataclass(frozen=True)
class CameraInfo(JsonPart):
    """The rectified geometry the metres were computed with."""

    focal_px: Annotated[float, Field(gt=0, description="rectified focal length at the disparity's resolution, px")]
    baseline_m: Annotated[float, Field(gt=0, description="metres")]
    cx: Annotated[float | None, Field(description="principal point x, px")] = None
    cy: Annotated[float | None, Field(description="principal point y, px")] = None

    def geometry(self) -> StereoGeometry:
        """The camera model for projecting the result's points; without a principal point (a result
        that did not record one) pixels are relative to the optical axis (cx = cy = 0)."""
        return StereoGeometry(self.focal_px, self.baseline_m, self.cx or 0.0, self.cy or 0.0)


@with_config(_STRICT)
@dataclass(frozen=True)
class StereoInfo(JsonPart):
    """The stereo backend that computed the disparity."""

    backend: Annotated[str, Field(min_length=1)]
    max_disparity: Annotated[int, Field(ge=1, description="pixels")]
    valid_fraction: Annotated[Fraction | None, Field(description="share of pixels with a valid disparity")] = None


@with_config(_STRICT)
@dataclass(frozen=True)
class LightInfo(JsonPart):
    """The frame's light, as the learned segmenter measured it to read its confidences by
    (`branchrange.core.light_check`)."""

    light: Annotated[
        Literal["normal", "dark", "bright", "noisy"],
        Field(description="the class of light whose calibration the confidences went through"),
    ]
    median_grey: Annotated[float, Field(ge=0, le=255, description="median grey level of the left image")]
    noise_grey: Annotated[NonNegFloat, Field(description="sensor noise σ over the flattest blocks, grey levels")]
    message: Annotated[str, Field(description="what was measured and what it means for the confidences")]

    @classmethod
    def from_reading(cls, reading: LightReading) -> LightInfo:
        """The written form of a `light_check.LightReading` (grey levels to 0.1)."""
        return cls(
            reading.light,  # type: ignore[arg-type]
            round(reading.median_grey, 1),
            round(reading.noise_grey, 2),
            reading.message,
        )


@with_config(_STRICT)
@dataclass(frozen=True)
class SegmenterOod(JsonPart):
    """Whether the learned segmenter's model looks like it knows this scene (`segmentation.ood`): how much more
    it hesitates over open background than on its training domain (the reference in the model's JSON)."""

    score: Annotated[
        Fraction,
        Field(description="share of the reference's held-out training-domain frames that lie nearer (0.5 typical)"),
    ]
    z: Annotated[
        float,
        Field(
            description="the frame's share of hesitant background (log) in standard deviations above the training "
            "domain's mean"
        ),
    ]
    flagged: Annotated[
        bool,
        Field(description="true when the frame hesitates more than 99 % of training-domain frames"),
    ]

    @classmethod
    def from_reading(cls, reading: OodReading) -> SegmenterOod:
        """The written form of a `segmentation.ood.OodReading`."""
        return cls(float(reading.score), float(reading.z), bool(reading.flagged))


@with_config(_STRICT)
@dataclass(frozen=True)
class MasksInfo(JsonPart):
    """Where the branch masks came from."""

    source: Annotated[str, Field(description="'file', 'array', a mask file's path or the segmenter's name")]
    instances: Annotated[int, Field(ge=0, description="branch instances in the mask")]
    trunk: Annotated[bool | None, Field(description="whether a trunk was known")] = None
    light: LightInfo | None = None


@with_config(_STRICT)
@dataclass(frozen=True)
class Branch(JsonPart):
    """One branch's cut point and geometry, rounded as written (mm for lengths, 1e-4 for shares)."""

    id: Annotated[int, Field(ge=0, description="branch id, stable across frames when tracking is on")]
    mask_id: Annotated[int, Field(ge=0, description="instance id in this frame's mask")]
    cut_point_m: Annotated[Vector3, Field(description="[x, y, z] metres, camera frame (x right, y down, z forward)")]
    distance_m: Annotated[float, Field(ge=0, description="camera origin to cut point, metres")]
    pixel: Annotated[tuple[float, float], Field(description="[u, v] of the cut point in the rectified left image, px")]
    diameter_m: Annotated[float, Field(ge=0, description="branch diameter at the cut, metres")]
    axis: Annotated[Vector3, Field(description="unit vector base → tip, camera frame")]
    base_m: Annotated[Vector3, Field(description="where the branch meets the trunk (or its thicker end), metres")]
    confidence: Fraction
    valid_fraction: Annotated[Fraction, Field(description="share of the eroded mask with valid disparity")]
    residual_m: Annotated[float, Field(ge=0, description="robust axis-fit residual, metres")]
    points: Annotated[int, Field(ge=0, description="3D points the fit used")]
    light_refuses_target: Annotated[
        bool | None,
        Field(
            description="true when the segmenter's calibration refuses this cut point as a target: the frame's light "
            "asks more confidence than it has (the calibration in that light), or its model carries no calibration "
            "at all; left out otherwise"
        ),
    ] = None
    disparity_scale: Annotated[
        int | None,
        Field(
            ge=2,
            description="its disparity was matched on the pair shrunk this many times (the roi mode's region "
            "budget, near the tree): its disparity noise is that many full-resolution pixels, and its "
            "covariance says so; absent: at full resolution",
        ),
    ] = None

    @classmethod
    def from_estimate(cls, b: BranchEstimate) -> Branch:
        """The written form of a `cutpoints.BranchEstimate`: plain floats, rounded (mm, 0.01 px, 1e-4)."""
        return cls(
            id=int(b.id),
            mask_id=int(b.mask_id),
            cut_point_m=_rounded3(b.cut_point_m),
            distance_m=round(float(b.distance_m), 5),
            pixel=(round(float(b.pixel[0]), 2), round(float(b.pixel[1]), 2)),
            diameter_m=round(float(b.diameter_m), 5),
            axis=_rounded3(b.axis),
            base_m=_rounded3(b.base_m),
            confidence=round(float(b.confidence), 4),
            valid_fraction=round(float(b.valid_fraction), 4),
            residual_m=round(float(b.residual_m), 5),
            points=int(b.n_points),
            disparity_scale=int(b.working_scale) if b.working_scale > 1 else None,
        )


def _rounded3(vector: Any) -> Vector3:
    """A (3,) vector as three plain floats rounded to 1e-5 (0.01 mm, or 1e-5 of a unit vector)."""
    x, y, z = (round(float(v), 5) for v in vector)
    return x, y, z


@with_config(_STRICT)
@dataclass(frozen=True)
class DroppedInstance(JsonPart):
    """A mask instance that gave no cut point, and why."""

    mask_id: NonNegInt
    reason: str

    @classmethod
    def from_dropped(cls, d: DroppedBranch) -> DroppedInstance:
        """The written form of a `cutpoints.DroppedBranch`."""
        return cls(int(d.mask_id), d.reason)


@with_config(_STRICT)
@dataclass(frozen=True)
class RoiRegion(JsonPart):
    """One full-resolution region matched in stereo mode 'roi'."""

    id: Annotated[
        int,
        Field(
            description="the instance it was planned for: its id in this frame's mask, or with the learned "
            "segmenter (roi.full_resolution_instances) in the coarse pass, whose instances are found again"
        ),
    ]
    box: Annotated[
        tuple[NonNegInt, NonNegInt, NonNegInt, NonNegInt], Field(description="[x0, y0, x1, y1] pixels, exclusive ends")
    ]
    d_min: Annotated[int, Field(ge=0, description="smallest disparity searched, pixels")]
    d_range: Annotated[int, Field(ge=1, description="disparities searched from d_min, pixels")]
    backend: Annotated[str, Field(description="the backend that matched it (SGBM beyond roi.network_regions)")]
    scale: Annotated[
        int | None,
        Field(
            ge=2,
            description="the region budget matched it on the pair shrunk this many times (roi.budget; "
            "absent: at full resolution)",
        ),
    ] = None

    @classmethod
    def from_region(cls, region: Region) -> RoiRegion:
        """The written form of a `roi.Region`."""
        x0, y0, x1, y1 = region.box
        scale = region.scale if region.scale > 1 else None
        return cls(region.instance_id, (x0, y0, x1, y1), region.d_min, region.d_range, region.backend, scale)


@with_config(_STRICT)
@dataclass(frozen=True)
class RoiInfo(JsonPart):
    """Stereo mode 'roi' only: the regions matched at full resolution, one per instance."""

    regions: tuple[RoiRegion, ...]


@with_config(_STRICT)
@dataclass(frozen=True)
class PairCheckInfo(JsonPart):
    """How far apart the rows of the rectified pair are, from feature matches (`branchrange.core.pair_check`)."""

    median_dy_px: Annotated[
        NonNegFloat | None, Field(description="median |y_left − y_right| of the matches, px; null when unknown")
    ]
    matches: Annotated[int, Field(ge=0, description="feature matches the estimate rests on")]
    status: Annotated[
        Literal["ok", "warning", "unknown"],
        Field(description="'ok' (≤ 1 px), 'warning' (> 1 px: rectify or calibrate) or 'unknown'"),
    ]
    message: Annotated[str, Field(description="the verdict and how to fix a misaligned pair")]

    @classmethod
    def from_check(cls, check: PairCheck) -> PairCheckInfo:
        """The written form of a `pair_check.PairCheck` (a refused pair never gets this far)."""
        return cls(check.median_dy_px, check.matches, check.status, check.message)  # type: ignore[arg-type]


@with_config(_STRICT)
@dataclass(frozen=True)
class Latency(JsonPart):
    """Onboard daemon only: milliseconds from the frame's arrival (monotonic clock) to each hand-over."""

    capture_to_stereo_ms: Annotated[NonNegFloat | None, Field(description="arrival → start of the stereo stage")] = None
    capture_to_geometry_ms: Annotated[
        NonNegFloat | None, Field(description="arrival → start of the geometry stage")
    ] = None
    capture_to_publish_ms: Annotated[
        NonNegFloat | None, Field(description="arrival → result handed to the MAVLink relay")
    ] = None


@with_config(_STRICT)
@dataclass(frozen=True)
class Freshness(JsonPart):
    """GET /latest only: how old the result is when it is served. The daemon keeps serving its newest result
    while the camera stalls; this says how stale it has become (the relay already sends it as "no target")."""

    age_s: Annotated[
        NonNegFloat, Field(description="seconds from the frame's capture (daemon's monotonic clock) to this request")
    ]
    stale: Annotated[bool, Field(description="true when age_s is over max_age_s: too old to act on")]
    max_age_s: Annotated[float, Field(gt=0, description="the daemon's mavlink.max_result_age_s, seconds")]


@with_config(_STRICT)
@dataclass(frozen=True)
class WorldTrack(JsonPart):
    """A cut point fused across frames in the autopilot's local NED frame (`mavlink.world_tracks`)."""

    id: Annotated[int, Field(ge=0, description="track id (OBSTACLE_DISTANCE_3D obstacle_id)")]
    branch_id: Annotated[int, Field(ge=0, description="the branch id it was last matched to")]
    ned_m: Annotated[Vector3, Field(description="fused position, local NED metres")]
    sigma_m: Annotated[
        float, Field(ge=0, description="1-σ radius (square root of the covariance's largest eigenvalue), metres")
    ]
    covariance_m2: Annotated[tuple[Vector3, Vector3, Vector3], Field(description="3×3 covariance, m²")]
    age_s: Annotated[float, Field(ge=0, description="seconds since its newest observation was captured")]
    observations: Annotated[int, Field(ge=1)]
    confidence: Annotated[
        Fraction,
        Field(description="recency-weighted confidence of its observations (tracking.confidence_half_life_s)"),
    ]
    # added in 0.2.0, optional so that older logs still read
    consistent_observations: Annotated[
        int | None, Field(ge=1, description="observations in a row within tracking.consistency_m of the track")
    ] = None
    views: Annotated[int | None, Field(ge=1, description="distinct viewpoints its observations came from")] = None


@with_config(_STRICT)
@dataclass(frozen=True)
class WorldTargets(JsonPart):
    """Onboard daemon with a MAVLink relay: the cut points fused in local NED, as they stand after this frame."""

    frame: Annotated[
        Literal["local_ned", "camera"],
        Field(description="'local_ned' while vehicle state is in use, 'camera' without it"),
    ]
    target_track_id: Annotated[
        int | None,
        Field(
            description="the target's track: consistent, confident and captured within mavlink.max_result_age_s "
            "(world_tracks.TargetRule); null when none is"
        ),
    ]
    tracks: tuple[WorldTrack, ...]


@with_config(_STRICT)
@dataclass(frozen=True, kw_only=True)
class FrameResult(JsonPart):
    """Cut points of the branches seen in one stereo frame (`branchrange/v1`).

    `timing_ms`: milliseconds per stage ('rectify', 'stereo', 'masks', 'cutpoints', 'tracking', 'total'
    and, in roi mode, the coarse and fine passes); treat it as read-only. `reason` says why there are
    no branches or no target, when so. `roi`, `pair_check`, `latency` and `targets` are there only when
    the stage that gives them ran (roi mode, the pair check, the daemon, a MAVLink relay); `freshness`
    only in the answer of GET /latest (never in a results log: it is the age at the time of a request).
    """

    schema: Literal["branchrange/v1"] = SCHEMA_ID
    frame: Frame
    camera: CameraInfo
    stereo: StereoInfo
    timing_ms: Annotated[
        dict[str, NonNegFloat], Field(json_schema_extra={"required": ["rectify", "stereo", "cutpoints", "total"]})
    ]
    masks: MasksInfo
    branches: tuple[Branch, ...]
    dropped: Annotated[
        tuple[DroppedInstance, ...], Field(description="mask instances that gave no cut point, with the reason")
    ]
    target_id: Annotated[
        int | None, Field(description="id of the branch to approach; null when none is confident enough")
    ]
    reason: Annotated[str | None, Field(description="why there are no branches or no target, when so")] = None
    roi: RoiInfo | None = None
    pair_check: PairCheckInfo | None = None
    latency: Latency | None = None
    targets: WorldTargets | None = None
    freshness: Freshness | None = None
    origin: Annotated[
        Literal["keyframe", "tracked"] | None,
        Field(
            description="with [roi] keyframe_interval_s > 0: 'keyframe' when the segmenter ran on this frame, "
            "'tracked' when its instances were carried over from the last frame"
        ),
    ] = None
    keyframe_age_s: Annotated[
        NonNegFloat | None, Field(description="seconds from the keyframe its instances descend from (0 on a keyframe)")
    ] = None
    segmenter_ood: SegmenterOod | None = None

    def __post_init__(self) -> None:
        if self.target_id is not None and all(b.id != self.target_id for b in self.branches):
            raise ResultFormatError(f"target_id = {self.target_id}: no branch has that id")

    @property
    def target(self) -> Branch | None:
        """The branch to approach (the one `target_id` names), or None when no branch is confident enough."""
        return next((b for b in self.branches if b.id == self.target_id), None)

    def is_target(self, branch: Branch) -> bool:
        """Whether `branch` is this frame's target."""
        return self.target_id is not None and branch.id == self.target_id

    @classmethod
    def from_json_dict(cls, data: Any) -> FrameResult:
        """A result from its `branchrange/v1` JSON object (a results-log line, an HTTP body).

        Raises `ResultFormatError` naming the first wrong key (e.g. `branches.0.distance_m`).
        """
        try:
            return _adapter().validate_python(data)
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(part) for part in first["loc"]) or "result"
            raise ResultFormatError(f"not a {SCHEMA_ID} result: {where}: {first['msg']}") from None


@cache
def _adapter() -> TypeAdapter[FrameResult]:
    """The pydantic adapter of `FrameResult` (built once: it compiles a validator)."""
    return TypeAdapter(FrameResult)


def _to_json(value: Any) -> Any:
    """Dataclasses → dicts (fields in order; a None field whose default is None left out), tuples → lists."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        out = {}
        for f in dataclasses.fields(value):
            item = getattr(value, f.name)
            if item is None and f.default is None:
                continue
            out[f.name] = _to_json(item)
        return out
    if isinstance(value, (tuple, list)):
        return [_to_json(v) for v in value]
    if isinstance(value, dict):
        return {k: _to_json(v) for k, v in value.items()}
    return value


def json_schema() -> dict[str, Any]:
    """The `branchrange/v1` JSON schema (draft 2020-12), generated from `FrameResult`."""
    schema = _adapter().json_schema()
    schema["required"] = ["schema", *schema["required"]]
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "https://branchrange.invalid/schemas/result_v1.json",
        "title": f"{SCHEMA_ID} frame result",
        **{k: v for k, v in schema.items() if k != "title"},
    }


def write_json_schema(path: str | Path = SCHEMA_PATH) -> Path:
    """Write `json_schema()` to `path` (default: the package's copy); run after changing a result class."""
    path = Path(path)
    path.write_text(json.dumps(json_schema(), indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
    return path
