"""Request-validation errors in the shape the OpenAPI document promises: `ErrorBody`, one string.

FastAPI answers a request that fails its declared parameters (a missing `left`, `max_disp=abc`)
with 422 and `{"detail": [{"loc": …, "msg": …}, …]}`; every other error of this API is
`{"detail": "…"}`. The handler here folds the list into one message naming each field, so a
client parses one error shape and the document describes what is sent.
"""

from __future__ import annotations

from typing import Any

from fastapi import Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

#: Longest repr of a rejected value repeated in a message.
MAX_VALUE_CHARS = 40


def _field(location: tuple[Any, ...] | list[Any]) -> str:
    """`("body", "max_disp")` → `max_disp`; nested locations joined with dots."""
    parts = [str(part) for part in location if part not in ("body", "query", "path", "header", "cookie")]
    return ".".join(parts) or "request"


def validation_message(errors: list[dict[str, Any]]) -> str:
    """One line per failed field: `max_disp = 'abc': Input should be a valid integer`."""
    lines = []
    for error in errors:
        field = _field(error.get("loc", ()))
        if error.get("type") == "missing":
            lines.append(f"{field}: required but missing")
            continue
        value = repr(error.get("input"))
        if len(value) > MAX_VALUE_CHARS:
            value = value[: MAX_VALUE_CHARS - 1] + "…"
        lines.append(f"{field} = {value}: {error.get('msg', 'invalid')}")
    return "; ".join(lines)


async def validation_error_answer(request: Request, exc: RequestValidationError) -> JSONResponse:
    """The exception handler for `RequestValidationError`: 422 with an `ErrorBody`."""
    return JSONResponse({"detail": validation_message(list(exc.errors()))}, status.HTTP_422_UNPROCESSABLE_CONTENT)
