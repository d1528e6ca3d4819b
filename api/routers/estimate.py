"""POST /estimate and POST /disparity: a multipart stereo pair in, cut points or disparity out.

Both take the same pair and camera fields (`stereo_request`, a dependency, so the OpenAPI
document describes them once and alike); /estimate adds a mask, /disparity an output format.
"""

from __future__ import annotations

import io
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, File, Form, HTTPException, Request, Response, UploadFile, status
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from api.auth import require_token
from api.estimator import CameraSpec
from api.limits import decode_image, decode_mask, read_upload
from api.schemas import ErrorBody, EstimateResult
from branchrange.core.segmentation.choose import BUILTIN_SEGMENTERS
from branchrange.core.settings_check import PHYSICAL_RANGES, RangeError, check_calibration, check_physical
from stereo.backends import BACKEND_NAMES, MAX_DISP_EXPECTED, BackendConfigError, check_max_disp
from stereo.backends.base import StereoInputError, validate_pair

router = APIRouter(dependencies=[Depends(require_token)])

ERRORS: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorBody, "description": "a body that is not multipart/form-data (no boundary, malformed parts)"},
    401: {"model": ErrorBody, "description": "missing or wrong bearer token"},
    413: {"model": ErrorBody, "description": "body above api.max_upload_mb or an image above api.max_pixels"},
    415: {"model": ErrorBody, "description": "an image that is not PNG or JPEG"},
    422: {"model": ErrorBody, "description": "a field missing or out of range, an unreadable file or calibration"},
    503: {
        "model": ErrorBody,
        "description": "every inference slot is busy (answered before the body is read)",
        "headers": {
            "Retry-After": {"description": "seconds to wait (api.retry_after_s)", "schema": {"type": "integer"}}
        },
    },
}
Backend = Literal[BACKEND_NAMES]  # type: ignore[valid-type]  # the one list, stereo.backends


def _unprocessable(message: str) -> HTTPException:
    return HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, message)


@dataclass(frozen=True)
class StereoRequest:
    """A decoded upload: RGB `uint8 H×W×3` pair, its camera, and the stereo options asked for."""

    left: np.ndarray
    right: np.ndarray
    camera: CameraSpec
    backend: str | None
    max_disp: int | None


#: Longest client file name repeated in messages (the name is never used for a path).
MAX_NAME_CHARS = 64


def display_name(filename: str | None, default: str = "calibration") -> str:
    """The client's file name for messages only: its last path part, printable characters, at most
    `MAX_NAME_CHARS` (a NUL, `..` or 300 characters stay harmless)."""
    last = (filename or "").replace("\\", "/").rsplit("/", 1)[-1]
    name = "".join(ch for ch in last if ch.isprintable())
    if name in ("", ".", ".."):
        return default
    return name if len(name) <= MAX_NAME_CHARS else name[: MAX_NAME_CHARS - 1] + "…"


def _checked_calibration(data: bytes, name: str, resolution: str | None, size: tuple[int, int]) -> Any:
    """The upload as a `camera.StereoCalibration`, checked against the images' size and the
    physical ranges before the pipeline builds rectification maps from it."""
    from camera.load import load_calibration_bytes

    calibration = load_calibration_bytes(data, name, resolution, size=size)
    check_calibration(calibration, size, name)
    return calibration


async def _load_calibration(upload: UploadFile, resolution: str | None, size: tuple[int, int], max_bytes: int) -> Any:
    """A `camera.StereoCalibration` from an uploaded file of any format `camera` reads; 422 when it cannot be read."""
    data = await read_upload(upload, "calibration", max_bytes)
    name = display_name(upload.filename)
    try:
        return await run_in_threadpool(_checked_calibration, data, name, resolution, size)
    except ValueError as exc:
        raise _unprocessable(f"calibration: {exc}") from None
    except Exception as exc:  # noqa: BLE001 - an uploaded file is untrusted: a parser crash on it is bad input too
        raise _unprocessable(
            f"calibration: {name}: not a readable calibration file ({type(exc).__name__} in its parser)"
        ) from None


def _camera_value(quantity: str, value: float, field: str) -> float:
    """A focal length or baseline field checked against its physical range (422 naming it)."""
    try:
        return check_physical(quantity, value, field)
    except RangeError as exc:
        raise _unprocessable(str(exc)) from None


async def _decoded(upload: UploadFile, field: str, settings: Any) -> np.ndarray:
    """An uploaded image as RGB `uint8 H×W×3`, read and decoded off the event loop (4xx when unusable)."""
    data = await read_upload(upload, field, settings.max_upload_bytes)
    return await run_in_threadpool(decode_image, data, field, settings.max_pixels)


async def stereo_request(
    request: Request,
    left: Annotated[UploadFile, File(description="left image, PNG or JPEG")],
    right: Annotated[UploadFile, File(description="right image, PNG or JPEG, the left one's size")],
    calibration: Annotated[
        UploadFile | None,
        File(
            description="ZED .conf, OpenCV YAML/JSON/XML, depthai JSON or KITTI calib; the pair is raw and gets "
            "rectified (instead of focal_px + baseline_m)"
        ),
    ] = None,
    resolution: Annotated[str | None, Form(description="ZED .conf files: 2K, FHD, HD or VGA")] = None,
    focal_px: Annotated[
        float | None,
        Form(
            allow_inf_nan=False,
            description=(
                "rectified pair: focal length, pixels at the uploaded size (with baseline_m); "
                f"{PHYSICAL_RANGES['focal_px'].describe()}"
            ),
        ),
    ] = None,
    baseline_m: Annotated[
        float | None,
        Form(
            allow_inf_nan=False,
            description=(
                f"rectified pair: baseline, metres (with focal_px); {PHYSICAL_RANGES['baseline_m'].describe()}"
            ),
        ),
    ] = None,
    backend: Annotated[Backend | None, Form(description="stereo backend; the server's default when left out")] = None,
    max_disp: Annotated[int | None, Form(description=f"disparity search range: {MAX_DISP_EXPECTED}")] = None,
) -> StereoRequest:
    """The decoded pair and its `CameraSpec`; 4xx with a message for anything unusable."""
    settings = request.app.state.settings
    if max_disp is not None:
        try:
            check_max_disp(max_disp)
        except BackendConfigError as exc:
            raise _unprocessable(str(exc)) from None
    if calibration is not None and (focal_px is not None or baseline_m is not None):
        raise _unprocessable("give either a calibration file or focal_px + baseline_m, not both")
    if calibration is None and (focal_px is None or baseline_m is None):
        raise _unprocessable(
            "missing camera: upload a calibration file (with resolution for ZED files), "
            "or give focal_px and baseline_m of the rectified pair"
        )
    if calibration is None:  # checked before any image is decoded
        camera = CameraSpec(
            focal_px=_camera_value("focal_px", focal_px, "focal_px"),
            baseline_m=_camera_value("baseline_m", baseline_m, "baseline_m"),
        )
    left_img = await _decoded(left, "left", settings)
    right_img = await _decoded(right, "right", settings)
    try:
        validate_pair(left_img, right_img)  # the pair is checked here, once, for both routes
    except StereoInputError as exc:
        raise _unprocessable(str(exc)) from None
    if calibration is not None:
        size = (left_img.shape[1], left_img.shape[0])
        camera = CameraSpec(
            calibration=await _load_calibration(calibration, resolution, size, settings.max_upload_bytes)
        )
    return StereoRequest(left_img, right_img, camera, backend, max_disp)


async def _infer(request: Request, func: Any, *args: Any, **kwargs: Any) -> Any:
    """Run blocking `func` in the thread pool inside an inference slot; ValueError → 422."""
    state = request.app.state
    async with state.slots.slot():
        start = time.perf_counter()
        try:
            out = await run_in_threadpool(func, *args, **kwargs)
        except ValueError as exc:
            state.metrics.count_error("bad_input")
            raise _unprocessable(str(exc)) from None
        state.metrics.observe_frame(time.perf_counter() - start, "api")
        return out


@router.post(
    "/estimate", response_model=EstimateResult, responses=ERRORS, summary="Cut points of the branches in a stereo pair"
)
async def post_estimate(
    request: Request,
    pair: Annotated[StereoRequest, Depends(stereo_request)],
    mask: Annotated[
        UploadFile | None,
        File(
            description=(
                "instance-id PNG (0 = background, 8 or 16 bit) or binary mask, the left image's size; "
                "the server's segmenter runs when left out"
            )
        ),
    ] = None,
    segmenter: Annotated[
        Literal[("configured", *BUILTIN_SEGMENTERS)],
        Form(
            description=(
                "without a mask: 'configured' = the server's [segmenter] model (e.g. its onnx:FILE), "
                "'learned', 'structure' or 'geometric' = a built-in one"
            )
        ),
    ] = "configured",
) -> JSONResponse:
    """Stereo pair (+ optional mask) and camera → the `branchrange/v1` result."""
    settings = request.app.state.settings
    mask_arr = None
    if mask is not None:
        data = await read_upload(mask, "mask", settings.max_upload_bytes)
        mask_arr = await run_in_threadpool(decode_mask, data, "mask", settings.max_pixels)
        if mask_arr.shape != pair.left.shape[:2]:
            raise _unprocessable(
                f"mask is {mask_arr.shape[1]}×{mask_arr.shape[0]} px but the images are "
                f"{pair.left.shape[1]}×{pair.left.shape[0]} px; it must match the left image"
            )
    result = await _infer(
        request,
        request.app.state.estimator.estimate,
        pair.left,
        pair.right,
        mask_arr,
        pair.camera,
        backend=pair.backend,
        max_disp=pair.max_disp,
        segmenter=None if segmenter == "configured" else segmenter,
    )
    return JSONResponse(result.to_json_dict())


def _encode_kitti_png(disparity: np.ndarray) -> bytes:
    """KITTI 16-bit PNG bytes (value = disparity × 256, 0 = invalid) of a `float32 H×W` disparity."""
    from stereo.io import write_kitti_disparity

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "disparity.png"
        write_kitti_disparity(path, disparity)
        return path.read_bytes()


@router.post(
    "/disparity",
    responses={**ERRORS, 200: {"content": {"image/png": {}, "application/x-npy": {}}}},
    response_class=Response,
    summary="Disparity of a stereo pair (KITTI PNG or .npy)",
)
async def post_disparity(
    request: Request,
    pair: Annotated[StereoRequest, Depends(stereo_request)],
    format: Annotated[
        Literal["png", "npy"], Form(description="png: KITTI 16-bit (value/256 px); npy: float32")
    ] = "png",
) -> Response:
    """Disparity of the (rectified) left view in pixels; KITTI PNG by default, `.npy` on request."""
    disparity = await _infer(
        request,
        request.app.state.estimator.disparity,
        pair.left,
        pair.right,
        pair.camera,
        backend=pair.backend,
        max_disp=pair.max_disp,
    )
    if format == "npy":
        buffer = io.BytesIO()
        np.save(buffer, disparity.astype(np.float32))
        return Response(buffer.getvalue(), media_type="application/x-npy")
    try:
        return Response(await run_in_threadpool(_encode_kitti_png, disparity), media_type="image/png")
    except ValueError as exc:
        raise _unprocessable(f"{exc}; ask for format=npy") from None
