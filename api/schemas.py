"""Pydantic models of what the API returns, so that the OpenAPI document describes it.

The result (`EstimateResult`) is `branchrange.core.frame_result.FrameResult` itself, under the API's name:
the dataclasses that the pipeline returns, that the `branchrange/v1` JSON schema is generated from,
are the response model, so the three cannot drift apart. Routes answer with
`FrameResult.to_json_dict()` (optional parts the pipeline did not fill stay out rather than turning
into nulls): the API's JSON is the daemon's and the replay's. Units are metres, pixels and
milliseconds; 3D points are in the rectified left camera frame (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, Field

from branchrange.core.frame_result import FrameResult


@dataclass(frozen=True, kw_only=True)
class EstimateResult(FrameResult):
    """Cut points of the branches seen in one stereo pair or frame (`branchrange/v1`): `FrameResult`."""


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
