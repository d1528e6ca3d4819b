"""Resource limits of the service: request size, image pixels, and bounded inference concurrency.

Sizes are checked before work is done: the request body by `BodySizeLimit` as it arrives (FastAPI
parses a multipart body, spooling files to disk, before any dependency runs, so the limit has to
sit in front of the app), each upload while it is read, and an image's width × height from its
PNG/JPEG header before it is decoded (a small file can decode to gigabytes).
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import cv2
import numpy as np
from fastapi import HTTPException, UploadFile, status
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from branchrange.core.settings_check import RangeError, check_image_size

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8\xff"
#: JPEG start-of-frame markers (baseline, progressive, lossless …) that carry the image size.
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _unprocessable(message: str) -> HTTPException:
    return HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, message)


class InferenceSlots:
    """At most `capacity` inferences at once; when all are taken, 503 with Retry-After at once."""

    def __init__(self, capacity: int, retry_after_s: int):
        self.capacity = capacity
        self.retry_after_s = retry_after_s
        self._semaphore = asyncio.Semaphore(capacity)

    @property
    def in_use(self) -> int:
        """How many slots are taken now."""
        return self.capacity - self._semaphore._value  # noqa: SLF001 - asyncio exposes no public count

    @property
    def busy(self) -> bool:
        """Whether every slot is taken (a new inference would be refused)."""
        return self._semaphore.locked()

    def busy_answer(self) -> tuple[str, dict[str, str]]:
        """The 503's message and headers (`Retry-After`)."""
        return (
            f"all {self.capacity} inference slots are busy; retry in {self.retry_after_s} s",
            {"Retry-After": str(self.retry_after_s)},
        )

    @asynccontextmanager
    async def slot(self) -> AsyncIterator[None]:
        """Hold a slot for the body of the `async with`, or raise 503 without queueing."""
        if self.busy:
            raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, *self.busy_answer())
        async with self._semaphore:
            yield


class ShedWhenBusy:
    """ASGI middleware: 503 + Retry-After for an inference route while every slot is busy, before
    its body is read (an upload of megabytes would otherwise be received, spooled and decoded only
    to be refused). A request admitted here can still get the 503 of `InferenceSlots.slot` when
    the last slot was taken while it uploaded; holding the slot from here on instead would let a
    slow upload block inference for everyone.
    """

    def __init__(self, app: ASGIApp, slots: InferenceSlots, paths: frozenset[str]) -> None:
        self.app = app
        self.slots = slots
        self.paths = paths

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["path"] in self.paths and self.slots.busy:
            detail, headers = self.slots.busy_answer()
            response = JSONResponse(
                {"detail": detail}, status.HTTP_503_SERVICE_UNAVAILABLE, headers={**headers, "Connection": "close"}
            )
            await response(scope, receive, send)
            return
        await self.app(scope, receive, send)


def _body_too_large(size: int | str, limit: int) -> str:
    return f"request body of {size} bytes exceeds the limit of {limit} bytes (api.max_upload_mb)"


class BodySizeLimit:
    """ASGI middleware: 413 for a request body above `max_bytes`, before the app reads it.

    A declared Content-Length above the limit is answered at once; a body without one (chunked)
    is counted as it streams in and cut off with 413 at the first byte over the limit.
    """

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length", b"").decode("latin-1")
        if declared.isdigit() and int(declared) > self.max_bytes:
            response = JSONResponse(
                {"detail": _body_too_large(declared, self.max_bytes)},
                status.HTTP_413_CONTENT_TOO_LARGE,
                headers={"Connection": "close"},
            )
            await response(scope, receive, send)
            return
        received = 0

        async def counting_receive() -> Message:
            nonlocal received
            message = await receive()
            received += len(message.get("body", b""))
            if received > self.max_bytes:  # raised inside the route: FastAPI turns it into the response
                raise HTTPException(
                    status.HTTP_413_CONTENT_TOO_LARGE, _body_too_large(f"more than {self.max_bytes}", self.max_bytes)
                )
            return message

        await self.app(scope, counting_receive, send)


async def read_upload(upload: UploadFile, field: str, max_bytes: int) -> bytes:
    """The bytes of an uploaded file; 413 above `max_bytes`, 422 when empty."""
    data = await upload.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise HTTPException(
            status.HTTP_413_CONTENT_TOO_LARGE, f"{field}: file exceeds {max_bytes} bytes (api.max_upload_mb)"
        )
    if not data:
        raise _unprocessable(f"{field}: the uploaded file is empty")
    return data


def image_dimensions(data: bytes, field: str) -> tuple[int, int]:
    """(width, height) from a PNG or JPEG header without decoding; 415 for other formats."""
    if data.startswith(PNG_MAGIC) and len(data) >= 24 and data[12:16] == b"IHDR":
        return struct.unpack(">II", data[16:24])
    if data.startswith(JPEG_MAGIC):
        i = 2
        while i + 9 <= len(data):
            if data[i] != 0xFF:
                break
            marker, length = data[i + 1], struct.unpack(">H", data[i + 2 : i + 4])[0]
            if marker in _JPEG_SOF:
                height, width = struct.unpack(">HH", data[i + 5 : i + 9])
                return width, height
            i += 2 + length
        raise _unprocessable(f"{field}: a JPEG without a readable frame header (truncated or corrupt)")
    raise HTTPException(status.HTTP_415_UNSUPPORTED_MEDIA_TYPE, f"{field}: expected a PNG or JPEG image")


def _check_pixels(data: bytes, field: str, max_pixels: int) -> None:
    width, height = image_dimensions(data, field)
    try:
        check_image_size(width, height, f"{field} image size")
    except RangeError as exc:
        raise _unprocessable(str(exc)) from None
    if width * height > max_pixels:
        raise HTTPException(
            status.HTTP_413_CONTENT_TOO_LARGE,
            f"{field}: {width}×{height} = {width * height} pixels exceeds the limit of {max_pixels} (api.max_pixels)",
        )


def decode_image(data: bytes, field: str, max_pixels: int) -> np.ndarray:
    """A PNG/JPEG upload as RGB `uint8 H×W×3`, after the pixel-count check."""
    _check_pixels(data, field, max_pixels)
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise _unprocessable(f"{field}: the image could not be decoded (corrupt or truncated)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def decode_mask(data: bytes, field: str, max_pixels: int) -> np.ndarray:
    """A PNG mask (8/16-bit instance ids, or binary) as an `H×W` integer array."""
    _check_pixels(data, field, max_pixels)
    mask = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if mask is None:
        raise _unprocessable(f"{field}: the mask could not be decoded (corrupt or truncated)")
    if mask.ndim == 3:
        raise _unprocessable(
            f"{field}: a mask must be single-channel (instance ids or 0/255), got {mask.shape[2]} channels"
        )
    return mask
