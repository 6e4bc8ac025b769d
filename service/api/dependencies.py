"""FastAPI dependencies shared by the routers."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPBearer

from crestereo_pp.service.batching.runtime import ServiceRuntime
from crestereo_pp.service.settings import Settings


def get_runtime(request: Request) -> ServiceRuntime:
    runtime: ServiceRuntime = request.app.state.runtime
    return runtime


def get_settings(runtime: Annotated[ServiceRuntime, Depends(get_runtime)]) -> Settings:
    return runtime.settings


RuntimeDep = Annotated[ServiceRuntime, Depends(get_runtime)]
SettingsDep = Annotated[Settings, Depends(get_settings)]

_bearer = HTTPBearer(auto_error=False, description="Required only when the server sets `CRESTEREO_API_KEY`.")

API_KEY_SCHEME = Depends(_bearer)
"""A route's dependency that declares the optional bearer key in the OpenAPI contract (with
`openapi_extra={"security": [{}]}` beside it: the key is needed only where the server sets one).
It checks nothing: `ApiKeyMiddleware` refuses every request without the key to a path that is not
open, before any route runs."""


def bearer_accepted(settings: Settings, token: str | None) -> bool:
    """Whether a request bearing `token` (None: no bearer token) may use the service: always when
    no `CRESTEREO_API_KEY` is set, else when the token equals it (compared in constant time)."""
    if settings.api_key is None:
        return True
    return hmac.compare_digest((token or "").encode(), settings.api_key.encode())
