"""Bearer-token authentication as a FastAPI dependency (no token configured → open, loopback only).

The scheme is FastAPI's `HTTPBearer`, so the OpenAPI document names it (`securitySchemes`) on
every route that needs it; the check itself is ours (constant-time, one message for missing and
wrong tokens).
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

BEARER = HTTPBearer(auto_error=False, description="the token of `[api] token` or BRANCHRANGE_API_TOKEN")


def require_token(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)]
) -> None:
    """Reject the request with 401 unless it carries `Authorization: Bearer <the configured token>`."""
    token = request.app.state.settings.token
    if not token:
        return
    given = "" if credentials is None else credentials.credentials.strip()
    if not hmac.compare_digest(given.encode(), token.encode()):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing or wrong bearer token (Authorization: Bearer …)",
            headers={"WWW-Authenticate": "Bearer"},
        )
