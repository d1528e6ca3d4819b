"""POST /estimate and POST /disparity: a multipart stereo pair in, cut points or disparity out."""
from __future__ import annotations

import io
import tempfile
import time
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Depends, File, Form, HTTPException, Request, Response, UploadFile, status
from starlette.concurrency import run_in_threadpool

from api.auth import require_token
from api.estimator import CameraSpec
from api.limits import check_content_length, decode_image, decode_mask, read_upload
from api.schemas import ErrorBody, EstimateResult

router = APIRouter(dependencies=[Depends(require_token), Depends(check_content_length)])

ERRORS = {code: {"model": ErrorBody} for code in (401, 413, 415, 422, 503)}
Backend = Literal["sgbm", "emcstereo"]


def _unprocessable(message: str) -> HTTPException:
    return HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, message)


async def _load_calibration(upload: UploadFile, resolution: str | None, size: tuple[int, int], max_bytes: int):
    """A `camera.StereoCalibration` from an uploaded file of any format `camera` reads."""
    from camera import load_calibration

    data = await read_upload(upload, "calibration", max_bytes)
    name = Path(upload.filename or "calibration").name or "calibration"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        path.write_bytes(data)
        try:
            return await run_in_threadpool(load_calibration, path, resolution, size=size)
        except ValueError as exc:
            raise _unprocessable(f"calibration: {str(exc).replace(str(path), name)}") from None


async def _pair(request: Request, left: UploadFile, right: UploadFile, calibration: UploadFile | None,
                resolution: str | None, focal_px: float | None, baseline_m: float | None):
    """Decoded RGB pair and its `CameraSpec`; 4xx with a message for anything unusable."""
    settings = request.app.state.settings
    limit = settings.max_upload_bytes
    left_img = decode_image(await read_upload(left, "left", limit), "left", settings.max_pixels)
    right_img = decode_image(await read_upload(right, "right", limit), "right", settings.max_pixels)
    if left_img.shape != right_img.shape:
        raise _unprocessable(f"left is {left_img.shape[1]}×{left_img.shape[0]} px but right is "
                             f"{right_img.shape[1]}×{right_img.shape[0]} px; a stereo pair must match")
    has_fb = focal_px is not None or baseline_m is not None
    if calibration is not None and has_fb:
        raise _unprocessable("give either a calibration file or focal_px + baseline_m, not both")
    if calibration is not None:
        size = (left_img.shape[1], left_img.shape[0])
        camera = CameraSpec(calibration=await _load_calibration(calibration, resolution, size, limit))
    elif focal_px is not None and baseline_m is not None:
        camera = CameraSpec(focal_px=focal_px, baseline_m=baseline_m)
    else:
        raise _unprocessable("missing camera: upload a calibration file (with resolution for ZED files), "
                             "or give focal_px and baseline_m of the rectified pair")
    return left_img, right_img, camera


async def _infer(request: Request, func, *args, **kwargs):
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


@router.post("/estimate", response_model=EstimateResult, responses=ERRORS,
             summary="Cut points of the branches in a stereo pair")
async def post_estimate(
    request: Request,
    left: Annotated[UploadFile, File(description="left image, PNG or JPEG")],
    right: Annotated[UploadFile, File(description="right image, same size")],
    mask: Annotated[UploadFile | None, File(description="instance-id PNG (0 = background) or binary mask")] = None,
    calibration: Annotated[UploadFile | None, File(description="ZED .conf, OpenCV YAML/JSON, depthai JSON or KITTI calib")] = None,
    resolution: Annotated[str | None, Form(description="ZED files: 2K, FHD, HD or VGA")] = None,
    focal_px: Annotated[float | None, Form(gt=0, description="rectified focal length, pixels")] = None,
    baseline_m: Annotated[float | None, Form(gt=0, description="baseline, metres")] = None,
    backend: Annotated[Backend | None, Form()] = None,
    max_disp: Annotated[int | None, Form(gt=0, le=512, description="disparity search range, pixels")] = None,
) -> dict:
    """Stereo pair (+ optional mask) and camera → the `branchrange/v1` result."""
    settings = request.app.state.settings
    left_img, right_img, camera = await _pair(request, left, right, calibration, resolution, focal_px, baseline_m)
    mask_arr = None
    if mask is not None:
        mask_arr = decode_mask(await read_upload(mask, "mask", settings.max_upload_bytes), "mask", settings.max_pixels)
    return await _infer(request, request.app.state.estimator.estimate, left_img, right_img, mask_arr, camera,
                        backend=backend, max_disp=max_disp)


def _encode_kitti_png(disparity: np.ndarray) -> bytes:
    """KITTI 16-bit PNG bytes (value = disparity × 256, 0 = invalid) of a `float32 H×W` disparity."""
    from stereo.io import write_kitti_disparity

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "disparity.png"
        write_kitti_disparity(path, disparity)
        return path.read_bytes()


@router.post("/disparity", responses={**ERRORS, 200: {"content": {"image/png": {}, "application/x-npy": {}}}},
             response_class=Response, summary="Disparity of a stereo pair (KITTI PNG or .npy)")
async def post_disparity(
    request: Request,
    left: Annotated[UploadFile, File()],
    right: Annotated[UploadFile, File()],
    calibration: Annotated[UploadFile | None, File()] = None,
    resolution: Annotated[str | None, Form()] = None,
    focal_px: Annotated[float | None, Form(gt=0)] = None,
    baseline_m: Annotated[float | None, Form(gt=0)] = None,
    backend: Annotated[Backend | None, Form()] = None,
    max_disp: Annotated[int | None, Form(gt=0, le=512)] = None,
    format: Annotated[Literal["png", "npy"], Form(description="png: KITTI 16-bit (value/256 px); npy: float32")] = "png",
) -> Response:
    """Disparity of the (rectified) left view in pixels; KITTI PNG by default, `.npy` on request."""
    left_img, right_img, camera = await _pair(request, left, right, calibration, resolution, focal_px, baseline_m)
    disparity = await _infer(request, request.app.state.estimator.disparity, left_img, right_img, camera,
                             backend=backend, max_disp=max_disp)
    if format == "npy":
        buffer = io.BytesIO()
        np.save(buffer, disparity.astype(np.float32))
        return Response(buffer.getvalue(), media_type="application/x-npy")
    try:
        return Response(await run_in_threadpool(_encode_kitti_png, disparity), media_type="image/png")
    except ValueError as exc:
        raise _unprocessable(f"{exc}; ask for format=npy") from None
