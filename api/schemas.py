"""Pydantic models of what the API returns, so that the OpenAPI document describes it.

`EstimateResult` mirrors the `branchrange/v1` JSON schema (branchrange/schemas/result_v1.json):
units are metres, pixels and milliseconds; 3D points are in the rectified left camera frame
(x right, y down, z forward). Extra keys the pipeline adds are passed through.
"""
from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field


class Frame(BaseModel):
    model_config = ConfigDict(extra="allow")
    index: int
    timestamp_ns: int = Field(description="monotonic capture time, nanoseconds (0 for uploads)")
    width: int = Field(description="pixels")
    height: int = Field(description="pixels")


class CameraInfo(BaseModel):
    model_config = ConfigDict(extra="allow")
    focal_px: float = Field(description="rectified focal length, pixels at this resolution")
    baseline_m: float = Field(description="metres")


class StereoInfo(BaseModel):
    model_config = ConfigDict(extra="allow")
    backend: str
    max_disparity: int = Field(description="pixels")


class Branch(BaseModel):
    model_config = ConfigDict(extra="allow")
    id: int
    cut_point_m: list[float] = Field(description="[x, y, z] metres, camera frame (x right, y down, z forward)")
    distance_m: float = Field(description="camera origin to cut point, metres")
    pixel: list[float] = Field(description="[u, v] of the cut point in the rectified left image")
    diameter_m: float | None = None
    axis: list[float] | None = Field(None, description="unit vector base → tip, camera frame")
    base_m: list[float] | None = None
    confidence: float = Field(ge=0.0, le=1.0)


class EstimateResult(BaseModel):
    """One frame's cut points (`branchrange/v1`)."""

    model_config = ConfigDict(extra="allow")
    schema_: str = Field("branchrange/v1", alias="schema")
    frame: Frame
    camera: CameraInfo
    stereo: StereoInfo
    timing_ms: dict[str, float]
    branches: list[Branch]
    target_id: int | None = Field(description="id of the branch to cut next, null when none")


class Health(BaseModel):
    status: str = Field(description="'ok', or 'degraded' when the camera is lost or the link is down")
    model: dict[str, Any]
    camera: dict[str, Any] | None = Field(None, description="daemon mode: camera source state")
    mavlink: dict[str, Any] | None = Field(None, description="daemon mode: MAVLink link state")


class Version(BaseModel):
    name: str
    version: str
    schema_: str = Field(alias="schema")
    api: str


class ErrorBody(BaseModel):
    detail: str
