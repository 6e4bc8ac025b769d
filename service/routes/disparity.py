"""`POST /disparity`: a rectified stereo pair in, disparity and uncertainty (and depth) out.

The route keeps HTTP: options, headers, readiness and the answer's headers. Uploads are read and
checked by `service.uploads`, the maps are rendered by `service.encoding.render`, and what the
batcher raises is answered by the error handlers (`service.errors.batching_answer`).
"""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Query, Request, Response
from starlette.concurrency import run_in_threadpool

from service.batching import Batcher, JobResult
from service.dependencies import RuntimeDep, require_api_key
from service.disparity_docs import RESPONSES, UPLOAD_BODY
from service.encoding import render
from service.errors import ApiError, bad_input, draining
from service.images import ImageHeader
from service.logs import request_id_var
from service.runtime import ServiceRuntime, weights_identity
from service.scheduling import Knobs
from service.schemas import DisparityOptions, DisparityResponse
from service.uploads import check_headers, decode_pair, read_uploads

router = APIRouter(tags=["disparity"])

MAX_TIMEOUT_MS = 3_600_000


@router.post(
    "/disparity",
    summary="Disparity and uncertainty of a rectified stereo pair",
    response_model=DisparityResponse,
    responses=RESPONSES,
    # `{}` beside the bearer scheme: the key is optional (only when CRESTEREO_API_KEY is set).
    openapi_extra={"requestBody": UPLOAD_BODY, "security": [{}]},
    dependencies=[Depends(require_api_key)],
)
async def estimate_disparity(
    request: Request,
    runtime: RuntimeDep,
    options: Annotated[DisparityOptions, Query()],
    timeout_ms: Annotated[
        int | None,
        Header(
            alias="X-Request-Timeout-Ms",
            ge=1,
            le=MAX_TIMEOUT_MS,
            description="Deadline in milliseconds from arrival: a request that cannot be computed "
            "in time is dropped before computing and answered 503 `deadline_exceeded`.",
        ),
    ] = None,
) -> Response:
    """Send the two images as multipart files `left` and `right`; options go in the query string.

    Every answer carries the model, the weights' identity, the image size, the batch size the
    request ran in and its timings (in the JSON body for `format=json`, and as `X-*` headers).
    """
    deadline = None if timeout_ms is None else time.monotonic() + timeout_ms / 1000
    request.state.model = options.model  # also read by the batching error handler
    _refuse_repeated_options(request)
    batcher = _batcher_for(runtime, options.model)
    left_bytes, right_bytes = await read_uploads(request)
    # header checks are pure Python over untrusted bytes: never on the event loop
    header = await run_in_threadpool(check_headers, runtime.settings, options.model, left_bytes, right_bytes)
    async with batcher.admit(options.model, pixels=header.pixels, deadline=deadline) as admission:
        left, right = await run_in_threadpool(decode_pair, left_bytes, right_bytes)
        result = await admission.run(
            left,
            right,
            knobs=Knobs(options.two_pass, options.iterations, options.scale, options.raw_uncertainty),
            deadline=deadline,
            is_disconnected=request.is_disconnected,
            request_id=request_id_var.get(),
        )
    request.state.batch_size = result.batch_size
    predictor = runtime.predictors[options.model]
    weights = weights_identity(predictor)
    content, media_type = await run_in_threadpool(render, options, result, left, weights, header)
    return Response(content, media_type=media_type, headers=_result_headers(predictor.name, weights, header, result))


def _refuse_repeated_options(request: Request) -> None:
    """`?model=lite&model=full` is ambiguous: 422 rather than silently taking one of them."""
    names = [name for name, _ in request.query_params.multi_items()]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise bad_input(422, "invalid_request", f"query.{repeated[0]}: given more than once")


def _batcher_for(runtime: ServiceRuntime, model: str) -> Batcher:
    if runtime.state == "failed":
        raise ApiError(
            503,
            "unavailable",
            "models failed to load; see the server log",
            reject_reason="not_ready",
            headers={"Retry-After": "60"},
        )
    if runtime.state == "draining":
        raise draining("server is shutting down")
    if runtime.state == "loading" or runtime.batcher is None:
        raise ApiError(
            503, "loading", "models are still loading", reject_reason="not_ready", headers={"Retry-After": "5"}
        )
    if model not in runtime.predictors:
        raise bad_input(
            422,
            "model_not_loaded",
            f"model `{model}` is not loaded by this server (loaded: {', '.join(runtime.predictors)})",
        )
    return runtime.batcher


def _result_headers(model: str, weights: str, size: ImageHeader, result: JobResult) -> dict[str, str]:
    """The result facts every answer carries as headers."""
    return {
        "X-Model": model,
        "X-Weights": weights,
        "X-Image-Size": f"{size.width}x{size.height}",
        "X-Batch-Size": str(result.batch_size),
        "X-Queue-Ms": f"{result.queue_seconds * 1000:.2f}",
        "X-Compute-Ms": f"{result.compute_seconds * 1000:.2f}",
    }
