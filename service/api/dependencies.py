"""FastAPI dependencies shared by the routers."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from crestereo_pp.service.api.errors import ApiError
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


def bearer_accepted(settings: Settings, token: str | None) -> bool:
    """Whether a request bearing `token` (None: no bearer token) may use the service: always when
    no `CRESTEREO_API_KEY` is set, else when the token equals it (compared in constant time)."""
    if settings.api_key is None:
        return True
    return hmac.compare_digest((token or "").encode(), settings.api_key.encode())


def require_api_key(
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """401 unless the bearer token equals `CRESTEREO_API_KEY` (`bearer_accepted`)."""
    if not bearer_accepted(settings, None if credentials is None else credentials.credentials):
        raise ApiError(401, "unauthorized", "missing or wrong bearer token", headers={"WWW-Authenticate": "Bearer"})
