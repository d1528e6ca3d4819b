"""Pydantic models of what the API returns, so that the OpenAPI document describes it.

`EstimateResult` mirrors the `branchrange/v1` JSON schema (branchrange/schemas/result_v1.json),
field for field (tests/test_api_estimate.py holds the two together): units are metres, pixels and
milliseconds; 3D points are in the rectified left camera frame (x right, y down, z forward).
Routes return results with `response_model_exclude_unset`, so optional keys the pipeline did not
write stay out rather than turning into nulls, and keys the schema gains later pass through: the
API's JSON is the daemon's and the replay's.
"""
from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

Vector3 = list[float]


class ResultPart(BaseModel):
    """A part of the `branchrange/v1` result; keys beyond the declared ones pass through."""

    model_config = ConfigDict(extra="allow")


class Frame(ResultPart):
    """Which frame the result is of."""

    index: int = Field(ge=0, description="frame number (0 for uploads)")
    timestamp_ns: int = Field(ge=0, description="monotonic capture time, nanoseconds (0 for uploads)")
    width: int = Field(ge=1, description="pixels")
    height: int = Field(ge=1, description="pixels")


class CameraInfo(ResultPart):
    """The rectified geometry metres were computed with."""

    focal_px: float = Field(gt=0, description="rectified focal length, pixels at the disparity's resolution")
    baseline_m: float = Field(gt=0, description="metres")
    cx: float | None = Field(None, description="principal point x, pixels")
    cy: float | None = Field(None, description="principal point y, pixels")


class StereoInfo(ResultPart):
    """The stereo backend that computed the disparity."""

    backend: str
    max_disparity: int = Field(ge=1, description="pixels")
    valid_fraction: float | None = Field(None, ge=0, le=1, description="share of pixels with a valid disparity")


class Timing(ResultPart):
    """Milliseconds per stage of this frame (`total` covers them all)."""

    rectify: float = Field(ge=0)
    stereo: float = Field(ge=0)
    masks: float | None = Field(None, ge=0)
    cutpoints: float = Field(ge=0)
    tracking: float | None = Field(None, ge=0)
    total: float = Field(ge=0)


class MasksInfo(ResultPart):
    """Where the branch masks came from."""

    source: str = Field(description="'file', 'array' or the segmenter's name")
    instances: int = Field(ge=0, description="branch instances in the mask")
    trunk: bool | None = Field(None, description="whether a trunk was known")


class PairCheckInfo(ResultPart):
    """How far apart the rows of the (rectified) pair are, from feature matches (`branchrange.pair_check`)."""

    median_dy_px: float | None = Field(description="median |y_left − y_right| of the matches, px; null when unknown")
    matches: int = Field(ge=0, description="feature matches the estimate rests on")
    status: str = Field(description="'ok' (≤ 1 px), 'warning' (> 1 px: rectify or calibrate) or 'unknown'")
    message: str = Field(description="the verdict and how to fix a misaligned pair")


class DroppedInstance(ResultPart):
    """A mask instance that gave no cut point."""

    mask_id: int = Field(ge=0)
    reason: str


class Branch(ResultPart):
    """One branch's cut point and geometry."""

    id: int = Field(ge=0, description="branch id, stable across frames when tracking is on")
    mask_id: int | None = Field(None, ge=0, description="instance id in this frame's mask")
    cut_point_m: Vector3 = Field(min_length=3, max_length=3, description="[x, y, z] metres, camera frame (x right, y down, z forward)")
    distance_m: float = Field(ge=0, description="camera origin to cut point, metres")
    pixel: list[float] = Field(min_length=2, max_length=2, description="[u, v] of the cut point in the rectified left image, pixels")
    diameter_m: float = Field(ge=0, description="branch diameter at the cut, metres")
    axis: Vector3 = Field(min_length=3, max_length=3, description="unit vector base → tip, camera frame")
    base_m: Vector3 = Field(min_length=3, max_length=3, description="where the branch meets the trunk (or its thicker end), metres, camera frame")
    confidence: float = Field(ge=0.0, le=1.0)
    valid_fraction: float | None = Field(None, ge=0, le=1, description="share of the mask with valid disparity")
    residual_m: float | None = Field(None, ge=0, description="robust axis-fit residual, metres")
    points: int | None = Field(None, ge=0, description="3D points the fit used")


class Latency(ResultPart):
    """Onboard daemon only: milliseconds from the frame's arrival to each hand-over."""

    capture_to_stereo_ms: float | None = Field(None, ge=0, description="arrival → start of the stereo stage")
    capture_to_geometry_ms: float | None = Field(None, ge=0, description="arrival → start of the geometry stage")
    capture_to_publish_ms: float | None = Field(None, ge=0, description="arrival → result handed to the MAVLink relay")


class RoiRegion(ResultPart):
    """One full-resolution region matched in stereo mode 'roi'."""

    id: int = Field(description="instance id in this frame's mask")
    box: list[int] = Field(min_length=4, max_length=4, description="[x0, y0, x1, y1] pixels, exclusive ends")
    d_min: int = Field(ge=0, description="smallest disparity searched, pixels")
    d_range: int = Field(ge=1, description="disparities searched from d_min, pixels")
    backend: str | None = Field(None, description="the backend that matched it (SGBM beyond roi.network_regions)")


class RoiInfo(ResultPart):
    """Stereo mode 'roi' only: the regions matched at full resolution."""

    regions: list[RoiRegion]


class WorldTrack(ResultPart):
    """A cut point fused across frames in the autopilot's local NED frame."""

    id: int = Field(ge=0, description="track id (OBSTACLE_DISTANCE_3D obstacle_id)")
    branch_id: int = Field(ge=0, description="the branch id it was last matched to")
    ned_m: Vector3 = Field(min_length=3, max_length=3, description="fused position, local NED metres")
    sigma_m: float = Field(ge=0, description="1-σ radius (square root of the covariance's largest eigenvalue), metres")
    covariance_m2: list[Vector3] = Field(min_length=3, max_length=3, description="3×3 covariance, m²")
    age_s: float = Field(ge=0, description="seconds since its newest observation was captured")
    observations: int = Field(ge=1)
    confidence: float = Field(ge=0, le=1, description="mean confidence of its observations")


class WorldTargets(ResultPart):
    """Onboard daemon with a MAVLink relay: the fused tracks after this frame."""

    frame: str = Field(description="'local_ned' while vehicle state is in use, 'camera' without it")
    target_track_id: int | None = Field(description="the target's track, null when none is fresh")
    tracks: list[WorldTrack]


class EstimateResult(ResultPart):
    """One frame's cut points (`branchrange/v1`)."""

    schema_: str = Field("branchrange/v1", alias="schema")
    frame: Frame
    camera: CameraInfo
    stereo: StereoInfo
    timing_ms: Timing
    masks: MasksInfo | None = None
    branches: list[Branch]
    dropped: list[DroppedInstance] | None = Field(None, description="mask instances that gave no cut point, with the reason")
    target_id: int | None = Field(description="id of the branch to cut next, null when none is confident enough")
    reason: str | None = Field(None, description="why there are no branches or no target, when so")
    latency: Latency | None = Field(None, description="onboard daemon only: how old the result was at each stage")
    roi: RoiInfo | None = Field(None, description="stereo mode 'roi' only: the regions matched at full resolution")
    targets: WorldTargets | None = Field(None, description="onboard daemon with MAVLink: cut points fused in local NED")
    pair_check: PairCheckInfo | None = Field(None, description="rectification check of the pair (above 8 px: 422)")


class Health(BaseModel):
    """Service state for probes and the ground crew."""

    status: str = Field(description="'ok', or 'degraded' when the camera is lost or the link is down")
    model: dict[str, Any] = Field(description="the stereo backend in use and the inference slots")
    camera: dict[str, Any] | None = Field(None, description="daemon mode: camera source state")
    mavlink: dict[str, Any] | None = Field(None, description="daemon mode: MAVLink link state")


class Version(BaseModel):
    """Package, result-schema and API versions."""

    name: str
    version: str
    schema_: str = Field(alias="schema")
    api: str


class ErrorBody(BaseModel):
    """A 4xx/5xx answer: what was wrong, naming the field or file."""

    detail: str
