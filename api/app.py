"""The app factory: `create_app(settings, estimator, state=None)` wires settings, auth, limits,
metrics and the routers (FastAPI "bigger applications" layout)."""

from __future__ import annotations

import time
from typing import Any, Protocol

from fastapi import FastAPI, Request, Response
from fastapi.exceptions import RequestValidationError

from api.docs import add_offline_docs
from api.errors import validation_error_answer
from api.estimator import Estimator
from api.limits import BodySizeLimit, InferenceSlots, ShedWhenBusy
from api.metrics import Metrics
from api.routers import estimate, status
from branchrange.config.sections import ApiConfig
from branchrange.core.frame_result import FrameResult

DESCRIPTION = """Cut points of tree branches, in metres, from a stereo pair.

`POST /estimate` returns one `branchrange/v1` result (3D points in the rectified left camera frame:
x right, y down, z forward, metres); `POST /disparity` the disparity map. With a token configured,
every route but `/health` and `/version` needs `Authorization: Bearer <token>`."""


class LiveStatus(Protocol):
    """What the onboard daemon exposes to the API (daemon mode)."""

    def latest_result(self) -> FrameResult | None:
        """The newest frame's result, or None before the first one."""
        ...

    def health(self) -> dict[str, Any]:
        """`{"camera": {...}, "mavlink": {...} | None, "model": {...}}` with at least `camera["lost"]`
        ("model", optional, describes the daemon's stereo backend)."""
        ...


def create_app(
    settings: ApiConfig, estimator: Estimator | None, state: LiveStatus | None = None, metrics: Metrics | None = None
) -> FastAPI:
    """The FastAPI app. `estimator` None leaves out the POST routes (a daemon that only reports);
    `state` (the daemon) enables `/latest` and the camera/link parts of `/health`."""
    app = FastAPI(
        title="BranchRange", version=status.package_version(), description=DESCRIPTION, docs_url=None, redoc_url=None
    )  # served from local assets: see add_offline_docs
    app.state.settings = settings
    app.state.estimator = estimator
    app.state.live = state
    app.state.metrics = metrics or Metrics()
    app.state.slots = InferenceSlots(settings.max_concurrency, settings.retry_after_s)
    app.add_exception_handler(RequestValidationError, validation_error_answer)
    # both inside the metrics middleware, so their 413s and 503s are counted
    app.add_middleware(
        ShedWhenBusy, slots=app.state.slots, paths=frozenset(route.path for route in estimate.router.routes)
    )
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_upload_bytes)

    @app.middleware("http")
    async def record_metrics(request: Request, call_next: Any) -> Response:
        start = time.perf_counter()
        response = await call_next(request)
        route = request.scope.get("route")
        app.state.metrics.observe_request(
            getattr(route, "path", "unmatched"), request.method, response.status_code, time.perf_counter() - start
        )
        return response

    if estimator is not None:
        app.include_router(estimate.router)
    app.include_router(status.router)
    add_offline_docs(app)
    return app
