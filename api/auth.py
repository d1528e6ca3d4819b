"""Bearer-token authentication as a FastAPI dependency (no token configured → open, loopback only)."""
from __future__ import annotations

import hmac

from fastapi import HTTPException, Request, status


def require_token(request: Request) -> None:
    """Reject the request with 401 unless it carries `Authorization: Bearer <the configured token>`."""
    token = request.app.state.settings.token
    if not token:
        return
    scheme, _, given = request.headers.get("authorization", "").partition(" ")
    if scheme.lower() != "bearer" or not hmac.compare_digest(given.strip().encode(), token.encode()):
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "missing or wrong bearer token (Authorization: Bearer …)",
                            headers={"WWW-Authenticate": "Bearer"})
