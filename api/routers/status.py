"""GET /health, /version (open, for probes), /metrics and /latest (token when one is set).

/health answers everyone, but the camera source path and the MAVLink URL (where the vehicle's
devices and peers are) only to a request with the token, when one is set.
"""

from __future__ import annotations

from importlib import metadata
from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Request, status
from fastapi.responses import JSONResponse, PlainTextResponse

from api.auth import BEARER, require_token
from api.health_metrics import health_metrics
from api.schemas import ErrorBody, EstimateResult, Health, Version
from branchrange.core.frame_result import SCHEMA_ID

router = APIRouter()
API_VERSION = "1"
#: /health keys shown only with the token: section → keys.
PRIVATE_HEALTH_KEYS = {"camera": ("source",), "mavlink": ("url",)}


def package_version() -> str:
    """The installed branchrange distribution's version."""
    try:
        return metadata.version("branchrange")
    except metadata.PackageNotFoundError:
        return "0+unknown"


async def _has_token(request: Request) -> bool:
    """Whether the request carries the configured token (True when none is configured)."""
    try:
        require_token(request, await BEARER(request))
    except HTTPException:
        return False
    return True


def health_body(state: Any) -> dict[str, Any]:
    """/health's whole body (private keys included): model, camera and link state, and 'ok' or 'degraded'."""
    estimator = state.estimator
    model = {
        "loaded": estimator is not None,
        "backend": getattr(estimator, "backend_name", None),
        "inference_slots": state.slots.capacity,
        "inference_in_use": state.slots.in_use,
    }
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


@router.get("/health", response_model=Health, summary="Model, camera and MAVLink link state")
async def get_health(request: Request) -> dict:
    """'ok', or 'degraded' when the daemon's camera is lost or its MAVLink link is down (no autopilot
    HEARTBEAT for 3 s). The camera source and the MAVLink URL are shown only with the token."""
    body = health_body(request.app.state)
    if not await _has_token(request):
        for section, keys in PRIVATE_HEALTH_KEYS.items():
            if body[section] is not None:
                body[section] = {k: v for k, v in body[section].items() if k not in keys}
    return body


@router.get("/version", response_model=Version, summary="Package, result-schema and API versions")
def get_version() -> dict:
    """Package, result-schema and API versions."""
    return {"name": "branchrange", "version": package_version(), "schema": SCHEMA_ID, "api": API_VERSION}


#: The 401 of /metrics is JSON like every error, though the route's own answer is text: written out,
#: since FastAPI would document a `model` under the route's media type (text/plain).
METRICS_401 = {
    "description": "missing or wrong bearer token",
    "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}},
}


@router.get(
    "/metrics",
    response_class=PlainTextResponse,
    dependencies=[Depends(require_token)],
    responses={401: METRICS_401},
    summary="Prometheus metrics (text format 0.0.4)",
)
def get_metrics(request: Request) -> PlainTextResponse:
    """Requests, latencies, frames and errors in the Prometheus text format, and every count and state
    /health gives (camera counters, the MAVLink link and its peer's mode and armed state in daemon mode)."""
    text = request.app.state.metrics.render() + "\n".join(health_metrics(health_body(request.app.state))) + "\n"
    return PlainTextResponse(text, media_type="text/plain; version=0.0.4")


@router.get(
    "/latest",
    response_model=EstimateResult,
    dependencies=[Depends(require_token)],
    responses={401: {"model": ErrorBody}, 404: {"model": ErrorBody}},
    summary="Daemon mode: the newest result and how old it is",
)
def get_latest(request: Request) -> JSONResponse:
    """The newest frame's result in daemon mode, with `freshness`: its age at this request (seconds since the
    frame's capture) and `stale` once that is over `mavlink.max_result_age_s` — while the camera stalls the
    last result stays here, stale. 404 outside daemon mode or before the first frame."""
    live = request.app.state.live
    if live is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "/latest exists in daemon mode only (branchrange daemon)")
    result = live.latest_result()
    if result is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, "no frame has been processed yet")
    return JSONResponse(result.to_json_dict())
