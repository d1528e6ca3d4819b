"""GET /health, /version (open, for probes), /metrics and /latest (token when one is set)."""
from __future__ import annotations

from importlib import metadata

from fastapi import APIRouter, Depends, HTTPException, Request, status
from fastapi.responses import PlainTextResponse

from api.auth import require_token
from api.schemas import ErrorBody, EstimateResult, Health, Version
from branchrange.pipeline import SCHEMA_ID

router = APIRouter()
API_VERSION = "1"


def package_version() -> str:
    """The installed branchrange distribution's version."""
    try:
        return metadata.version("branchrange")
    except metadata.PackageNotFoundError:
        return "0+unknown"


@router.get("/health", response_model=Health, summary="Model, camera and MAVLink link state")
def get_health(request: Request) -> dict:
    """'ok', or 'degraded' when the daemon's camera is lost or its MAVLink link is down."""
    state = request.app.state
    estimator = state.estimator
    model = {"loaded": estimator is not None, "backend": getattr(estimator, "backend_name", None),
             "inference_slots": state.slots.capacity, "inference_in_use": state.slots.in_use}
    body = {"status": "ok", "model": model, "camera": None, "mavlink": None}
    if state.live is not None:
        live = state.live.health()
        model.update(live.get("model") or {})  # the daemon's pipeline, when the API has no estimator of its own
        body.update(camera=live.get("camera"), mavlink=live.get("mavlink"))
        camera_lost = bool((body["camera"] or {}).get("lost"))
        link_down = body["mavlink"] is not None and not body["mavlink"].get("connected", False)
        if camera_lost or link_down:
            body["status"] = "degraded"
    return body


@router.get("/version", response_model=Version, summary="Package, result-schema and API versions")
def get_version() -> dict:
    """Package, result-schema and API versions."""
    return {"name": "branchrange", "version": package_version(), "schema": SCHEMA_ID, "api": API_VERSION}


#: The 401 of /metrics is JSON like every error, though the route's own answer is text: written out,
#: since FastAPI would document a `model` under the route's media type (text/plain).
METRICS_401 = {"description": "missing or wrong bearer token",
               "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}}}


@router.get("/metrics", response_class=PlainTextResponse, dependencies=[Depends(require_token)],
            responses={401: METRICS_401}, summary="Prometheus metrics (text format 0.0.4)")
def get_metrics(request: Request) -> PlainTextResponse:
    """Requests, latencies, frames and errors in the Prometheus text format."""
    return PlainTextResponse(request.app.state.metrics.render(), media_type="text/plain; version=0.0.4")


@router.get("/latest", response_model=EstimateResult, response_model_exclude_unset=True,
            dependencies=[Depends(require_token)],
            responses={401: {"model": ErrorBody}, 404: {"model": ErrorBody}}, summary="Daemon mode: the newest result")
def get_latest(request: Request) -> dict:
    """The newest frame's result in daemon mode; 404 outside it or before the first frame."""
    live = request.app.state.live
    if live is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "/latest exists in daemon mode only (branchrange daemon)")
    result = live.latest_result()
    if result is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "no frame has been processed yet")
    return result
