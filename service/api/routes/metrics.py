"""`GET /metrics`: Prometheus text exposition."""

from __future__ import annotations

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from crestereo_pp.service.api.dependencies import RuntimeDep

router = APIRouter(tags=["metrics"])


@router.head("/metrics", include_in_schema=False)
@router.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=Response,
    responses={
        200: {"description": "Prometheus text format.", "content": {"text/plain": {"schema": {"type": "string"}}}}
    },
)
async def metrics(runtime: RuntimeDep) -> Response:
    """Requests by model and status; latency, queue wait, compute and batch size histograms;
    queue depth; `crestereo_rejected_total{reason}`; process memory and CPU."""
    return Response(generate_latest(runtime.metrics.registry), media_type=CONTENT_TYPE_LATEST)
