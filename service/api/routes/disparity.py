"""`POST /disparity`: a stereo pair in (rectified, or raw with its calibration), disparity and
uncertainty (and depth) out.

The route keeps HTTP: options, headers, readiness, the body and the answer's headers. Uploads are
read and checked in the decoder processes (`service.uploads`), the pair is computed and its body
made by the pipeline it shares with `/disparity/stream` (`service.api.pipeline.answer_pair`), and
what the batcher raises is answered by the error handlers (`service.api.errors.batching_answer`).
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Callable
from functools import partial
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response
from pydantic import BaseModel, BeforeValidator
from starlette.requests import ClientDisconnect

from crestereo_pp.service.api.dependencies import API_KEY_SCHEME, RuntimeDep
from crestereo_pp.service.api.disparity_docs import RESPONSES, UPLOAD_BODY
from crestereo_pp.service.api.errors import ApiError, bad_input, client_gone
from crestereo_pp.service.api.logs import request_id_var
from crestereo_pp.service.api.pipeline import answer_pair
from crestereo_pp.service.api.query import repeated_option
from crestereo_pp.service.api.schemas import AnswerFacts, DisparityOptions, DisparityResponse
from crestereo_pp.service.batching.batcher import ClientDisconnected, DeadlineExceeded, Draining
from crestereo_pp.service.batching.runtime import ServiceRuntime
from crestereo_pp.service.uploads.multipart import ImageLimits, boundary_of

router = APIRouter(tags=["disparity"])

MAX_TIMEOUT_MS = 3_600_000
_ABANDON_POLL_S = 0.2  # how often a request whose images are being read checks whether it is abandoned


def _plain_digits(value: object) -> object:
    """`X-Request-Timeout-Ms` is plain digits, as numbers in the query are plain decimals:
    `3_600_000` or `+5` are refused, not read as numbers; and at most MAX_TIMEOUT_MS, said in words.
    0 passes: under the server's minimum, it is answered 503 `deadline_exceeded` as 1 is."""
    if isinstance(value, str) and not (value.isascii() and value.isdigit()):
        raise ValueError(f"expected a whole number of milliseconds such as 5000, got {value[:32]!r}")
    if isinstance(value, str) and int(value) > MAX_TIMEOUT_MS:
        raise ValueError(f"at most {MAX_TIMEOUT_MS} ms (an hour), got {value[:32]}")
    return value


@router.post(
    "/disparity",
    summary="Disparity and uncertainty of a stereo pair (rectified, or raw with its calibration)",
    response_model=DisparityResponse,
    responses=RESPONSES,
    # `{}` beside the bearer scheme: the key is optional (only when CRESTEREO_API_KEY is set).
    openapi_extra={"requestBody": UPLOAD_BODY, "security": [{}]},
    dependencies=[API_KEY_SCHEME],
)
async def estimate_disparity(
    request: Request,
    runtime: RuntimeDep,
    options: Annotated[DisparityOptions, Query()],
    timeout_ms: Annotated[
        int | None,
        Header(
            alias="X-Request-Timeout-Ms",
            ge=0,
            le=MAX_TIMEOUT_MS,
            description="Deadline in milliseconds from arrival: a request that cannot be computed "
            "in time is dropped before computing and answered 503 `deadline_exceeded`; so is one under the "
            "server's minimum (`CRESTEREO_MIN_TIMEOUT_MS`, 100 by default), at once.",
        ),
        BeforeValidator(_plain_digits),
    ] = None,
) -> Response:
    """Send the two images as multipart files `left` and `right`, and for a raw (unrectified) pair
    its camera's calibration as `calibration`; options go in the query string.

    Every answer carries the model, the weights' identity, the image size, the batch size the
    request ran in and its timings (in the JSON body for `format=json`, and as `X-*` headers).
    """
    deadline = None if timeout_ms is None else time.monotonic() + timeout_ms / 1000
    request.state.model = options.model  # for the access log and the metrics
    repeated = repeated_option(request.query_params.multi_items())
    if repeated is not None:
        raise bad_input(422, "invalid_request", repeated)
    _refuse_repeated_headers(request)
    batcher = runtime.batcher_for(options.model)
    settings = runtime.settings
    if timeout_ms is not None and timeout_ms < settings.min_timeout_ms:
        raise DeadlineExceeded(
            f"deadline cannot be met: X-Request-Timeout-Ms is {timeout_ms} ms, and no request is answered in "
            f"less than {settings.min_timeout_ms} ms here; send a longer deadline",
            batcher.retry_after(options.model),
        )
    content_type = request.headers.get("content-type", "")
    boundary_of(content_type)  # 415 before the body is read
    body = await _read_body(request, settings.body_timeout_s)
    stop = partial(_abandoned, request, deadline, runtime, partial(batcher.retry_after, options.model))
    limits = ImageLimits(options.model, settings.pixel_limit(options.model), settings.min_image_side)
    # Parsing and decoding untrusted bytes happen in the decoder processes, never here.
    upload = await runtime.decoders.read_pair(body, content_type, limits, stop)
    del body
    problem = options.calibration_problem(upload.rig is not None)
    if problem is not None:
        raise bad_input(422, "invalid_request", problem)
    answer = await answer_pair(
        runtime,
        batcher,
        options,
        upload,
        stop=stop,
        is_disconnected=request.is_disconnected,
        deadline=deadline,
        request_id=request_id_var.get(),
    )
    request.state.batch_size = answer.facts.batch_size
    headers = _result_headers(answer.facts, options.inference.align_rows)
    return Response(answer.body, media_type=answer.media_type, headers=headers)


async def _read_body(request: Request, timeout_s: float) -> bytes:
    """The whole request body (the middleware bounds its size), within `timeout_s` seconds: an
    upload that stalls cannot hold its buffer for longer (408)."""
    chunks: list[bytes] = []
    try:
        async with asyncio.timeout(timeout_s):
            async for chunk in request.stream():
                chunks.append(chunk)
    except TimeoutError:
        raise ApiError(
            408,
            "body_timeout",
            f"the request body did not arrive within {timeout_s:g} s",
            reject_reason="bad_input",
            headers={"Connection": "close"},
        ) from None
    except ClientDisconnect:  # gone mid-upload: nobody reads the answer; logged and counted as 499
        raise client_gone("client disconnected during the upload") from None
    return await asyncio.to_thread(b"".join, chunks)  # a copy of up to max_body_bytes: off the event loop


async def _abandoned(
    request: Request, deadline: float | None, runtime: ServiceRuntime, retry_after: Callable[[], int]
) -> Exception:
    """Resolves, with the error to answer, once the request's images need no longer be read or
    rectified: its client has gone, its deadline has passed (a retry likely succeeds after
    `retry_after()` s) or the drain is over."""
    while True:
        if runtime.drain_over.is_set():
            return Draining("drain timeout reached while this request's images were read or rectified")
        if deadline is not None and time.monotonic() >= deadline:
            return DeadlineExceeded(
                "the deadline passed while this request's images were read or rectified", retry_after()
            )
        if await request.is_disconnected():
            return ClientDisconnected("client disconnected while its images were read or rectified")
        await asyncio.sleep(_ABANDON_POLL_S)


def _refuse_repeated_headers(request: Request) -> None:
    """A repeated `X-Request-Timeout-Ms` is ambiguous: 422 rather than silently taking one."""
    if len(request.headers.getlist("x-request-timeout-ms")) > 1:
        raise bad_input(422, "invalid_request", "header.X-Request-Timeout-Ms: given more than once")


def header_fields(facts: BaseModel) -> str:
    """A model's fields as one header value: `name=value; ...` (JSON's spelling of each value)."""
    return "; ".join(f"{name}={json.dumps(value)}" for name, value in facts.model_dump().items())


def _result_headers(facts: AnswerFacts, rows_measured: bool) -> dict[str, str]:
    """The answer's facts as headers (`X-Camera` a raw pair's only, `X-Row-Offset` where the rows
    were measured: `unmeasured` where the pair had too little texture)."""
    headers = {
        "X-Model": facts.model,
        "X-Model-Status": facts.model_status,
        "X-Weights": facts.weights,
        "X-Image-Size": f"{facts.image_size.width}x{facts.image_size.height}",
        "X-Batch-Size": str(facts.batch_size),
        "X-Queue-Ms": f"{facts.timings.queue_ms:.2f}",
        "X-Compute-Ms": f"{facts.timings.compute_ms:.2f}",
    }
    if facts.camera is not None:
        headers["X-Camera"] = header_fields(facts.camera)
    if rows_measured:
        headers["X-Row-Offset"] = "unmeasured" if facts.row_offset is None else header_fields(facts.row_offset)
    return headers
