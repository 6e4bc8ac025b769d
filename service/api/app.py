"""The FastAPI application. Serve with `python -m crestereo_pp.service` (uvicorn with the limits
it is sized for)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from crestereo_pp.inference import load_model
from crestereo_pp.service.api.errors import install_error_handlers
from crestereo_pp.service.api.logs import configure_logging
from crestereo_pp.service.api.middleware import (
    ApiKeyMiddleware,
    ClientErrorPace,
    ClientErrorPaceMiddleware,
    ConcurrencyLimitMiddleware,
    RequestContextMiddleware,
    RequestSizeLimitMiddleware,
    UploadBudgetMiddleware,
)
from crestereo_pp.service.api.routes import disparity, docs, health, metrics, models, page, stream
from crestereo_pp.service.batching.runtime import ModelLoader, ServiceRuntime
from crestereo_pp.service.settings import Settings
from crestereo_pp.service.uploads.budgets import ByteBudget, StreamSlots
from crestereo_pp.service.uploads.memory import FreedMemory

API_VERSION = "1.0.0"  # version of the HTTP contract in openapi.yaml


def create_app(
    settings: Settings | None = None, loader: ModelLoader = load_model, load_before_serving: bool = False
) -> FastAPI:
    """Build the app; its lifespan loads the models once and runs the inference thread that computes the batches.

    settings: defaults to `Settings.from_env()` (the `CRESTEREO_*` variables).
    loader: `inference.load_model`, or a wrapper of it (tests inject faults through it).
    load_before_serving: the lifespan's startup returns only once the models are loaded (and
        fails where they cannot be), for a host that routes to an instance only after its startup
        (a Ray Serve replica); by default the app starts at once and answers 503 `loading` meanwhile.
    """
    settings = settings or Settings.from_env()
    configure_logging(settings.log_level)
    runtime = ServiceRuntime(settings, loader)

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        await runtime.start()
        try:
            if load_before_serving:
                await runtime.models_loaded()
            yield
        finally:
            await runtime.stop()

    app = FastAPI(
        title="CREStereo++ disparity service",
        version=API_VERSION,
        description="Dense disparity, uncertainty and metric depth from a rectified stereo pair, "
        "computed by CREStereo++ (`full`) or Lite-CREStereo++ (`lite`). Errors are JSON "
        '`{"error": {"code", "message"}}`; every response echoes `X-Request-Id`.',
        lifespan=lifespan,
        docs_url=None,  # served by service.api.routes.docs from the package, under a Content-Security-Policy
        redoc_url=None,  # no ReDoc: /docs is the one documentation page
    )
    app.state.runtime = runtime
    install_error_handlers(app, runtime.metrics)
    app.state.uploads = ByteBudget(settings.max_upload_bytes)  # request bodies
    app.state.stream_bytes = ByteBudget(settings.max_stream_bytes, "stream images")  # apart from the bodies'
    app.state.streams = StreamSlots(settings.max_streams, settings.max_streams_per_client)
    app.state.freed_memory = FreedMemory()  # given back after streams end and when no request is in progress
    app.add_middleware(UploadBudgetMiddleware, budget=app.state.uploads, metrics=runtime.metrics)
    app.add_middleware(RequestSizeLimitMiddleware, max_bytes=settings.max_body_bytes, metrics=runtime.metrics)
    app.add_middleware(
        ConcurrencyLimitMiddleware,
        max_requests=settings.max_requests,
        metrics=runtime.metrics,
        freed_memory=app.state.freed_memory,
    )
    app.add_middleware(ApiKeyMiddleware, settings=settings)  # before any limit: a refused request holds nothing
    app.add_middleware(  # outside the limits: an answer held back holds none of them
        ClientErrorPaceMiddleware,
        pace=ClientErrorPace(settings.client_error_rate, settings.client_error_burst),
        metrics=runtime.metrics,
    )
    app.add_middleware(RequestContextMiddleware, metrics=runtime.metrics)
    app.include_router(disparity.router)
    app.include_router(stream.router)
    app.include_router(health.router)
    app.include_router(metrics.router)
    app.include_router(models.router)
    app.include_router(docs.router)
    app.include_router(page.router)  # the web page at `/` and its files under /static/
    return app
