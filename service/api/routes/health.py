"""Health: a detailed `/health`, and the liveness / readiness probes Kubernetes expects. Each also
answers HEAD (load balancers and `curl -I` send it), left out of the schema as GET's twin."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from crestereo_pp.service.api.dependencies import RuntimeDep
from crestereo_pp.service.api.schemas import HealthResponse, ProbeResponse

router = APIRouter(tags=["health"])


@router.head("/health", include_in_schema=False)
@router.get(
    "/health",
    summary="Models, queues and batching configuration",
    response_model=HealthResponse,
    responses={
        503: {"model": HealthResponse, "description": "Loading, draining after SIGTERM, or models failed to load."}
    },
)
async def health(runtime: RuntimeDep) -> JSONResponse:
    """200 when ready to serve, else 503 with the same body."""
    body = runtime.health()
    return JSONResponse(body.model_dump(), status_code=200 if body.status == "ready" else 503)


@router.head("/health/live", include_in_schema=False)
@router.get(
    "/health/live",
    summary="Liveness probe",
    response_model=ProbeResponse,
    responses={
        503: {"model": ProbeResponse, "description": "Dead: models failed to load or the scheduler stopped; restart."}
    },
)
async def live(runtime: RuntimeDep) -> JSONResponse:
    """200 `alive` while the process can serve or is still starting; restart it on 503 `dead`."""
    alive = runtime.is_alive
    return JSONResponse({"status": "alive" if alive else "dead"}, status_code=200 if alive else 503)


@router.head("/health/ready", include_in_schema=False)
@router.get(
    "/health/ready",
    summary="Readiness probe",
    response_model=ProbeResponse,
    responses={503: {"model": ProbeResponse, "description": "`loading`, `draining` or `failed`."}},
)
async def ready(runtime: RuntimeDep) -> JSONResponse:
    """200 `ready` when requests are accepted; 503 with the state otherwise."""
    state = runtime.state
    return JSONResponse({"status": state}, status_code=200 if state == "ready" else 503)
