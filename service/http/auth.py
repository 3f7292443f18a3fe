"""API-key authentication: on when settings.api_key is set (docker-compose sets it), off otherwise."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Security
from fastapi.security import APIKeyHeader

from service.http.errors import ApiError
from core.settings import Settings, get_settings

API_KEY_HEADER = "X-API-Key"
# How the 401 is documented on every protected operation (OpenAPI).
UNAUTHORIZED_RESPONSE = {
    "description": f"the server requires an API key: {API_KEY_HEADER} is missing or does not match",
    "headers": {"WWW-Authenticate": {"description": "APIKey", "schema": {"type": "string"}}},
    "content": {"application/json": {"example": {"error": {
        "code": "unauthorized", "message": f"missing {API_KEY_HEADER} header: this server requires an API key",
        "details": None}}}}}
_header = APIKeyHeader(name=API_KEY_HEADER, auto_error=False,
                       description="required when the server has DENOISER_API_KEY set")


def require_api_key(settings: Annotated[Settings, Depends(get_settings)],
                    key: Annotated[str | None, Security(_header)] = None) -> None:
    if settings.api_key is None:
        return
    if key is None:
        raise ApiError(401, "unauthorized", f"missing {API_KEY_HEADER} header: this server requires an API key",
                       headers={"WWW-Authenticate": "APIKey"})
    if not hmac.compare_digest(key.encode(), settings.api_key.encode()):
        raise ApiError(401, "unauthorized", f"the {API_KEY_HEADER} header does not match this server's API key",
                       headers={"WWW-Authenticate": "APIKey"})


