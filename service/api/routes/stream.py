"""`/disparity/stream`: a WebSocket for video. One connection streams the pairs of one camera and
receives their maps in order, each frame warm-started from the previous one of the connection.

The protocol (service/README.md, "Streams"): the query string takes the options of
`POST /disparity` (but `frame`: a stream's pairs are rectified) and `warm_iters`; the client sends
each pair as two binary messages, the left image file then the right one, and receives one
message per pair: the answer in `format` (text for `json`, binary otherwise), or a text message
`{"error": {"code", "message"}, "frame": N}` for a frame that could not be computed (the
connection stays open). The same image limits, decoder processes, batching, and bearer key apply
as to `POST /disparity`: once its image headers pass, a pair goes through the pipeline that route
uses (`service.api.pipeline.answer_pair`).

What a stream may hold is bounded: a place among `max_streams` (`max_streams_per_client` per client
address), one pair at a time, each image no larger than `max_stream_image_bytes` and its model's
pixel limit allow and counted against the streams' own byte budget (`max_stream_bytes`, apart from
the request bodies'), and `stream_idle_timeout_s` to send each. A stream without a place (or
without the bearer key) is refused at the handshake, with an HTTP answer: it never opens, so it
holds no connection beyond that answer.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Awaitable, Callable, Iterator
from contextlib import ExitStack, contextmanager

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from pydantic import ValidationError
from starlette.responses import Response
from starlette.websockets import WebSocketState

from crestereo_pp.inference import WarmStart
from crestereo_pp.service.api.errors import ApiError, batching_answer, error_response, validation_problems
from crestereo_pp.service.api.pipeline import answer_pair
from crestereo_pp.service.api.query import repeated_option
from crestereo_pp.service.api.schemas import DisparityOptions, OutputFormat
from crestereo_pp.service.batching.batcher import BatchingError
from crestereo_pp.service.batching.runtime import ServiceRuntime
from crestereo_pp.service.uploads.budgets import ByteBudget, StreamSlots, largest_stream_image
from crestereo_pp.service.uploads.memory import FreedMemory
from crestereo_pp.service.uploads.multipart import ImageLimits, Upload, UploadError

logger = logging.getLogger(__name__)
router = APIRouter()

GOING_AWAY, UNSUPPORTED_DATA, POLICY_VIOLATION, MESSAGE_TOO_BIG, TRY_AGAIN_LATER = 1001, 1003, 1008, 1009, 1013
"""WebSocket close codes (RFC 6455, 7.4.1; 1013 from the IANA registry)."""
RETRY_AFTER_S = 1
"""`Retry-After` of a stream refused for want of a place (as of a request refused `overloaded`)."""


class _Closing(Exception):
    """End the stream: say why (`error` code and `reason`, unless `error` is None) in a last text
    message, then close with the WebSocket close `code`."""

    def __init__(self, code: int, error: str | None, reason: str) -> None:
        super().__init__(reason)
        self.code, self.error, self.reason = code, error, reason


@router.websocket("/disparity/stream")
async def stream_disparity(websocket: WebSocket) -> None:
    runtime: ServiceRuntime = websocket.app.state.runtime
    streams: StreamSlots = websocket.app.state.streams
    stream_bytes: ByteBudget = websocket.app.state.stream_bytes
    with streams.place(websocket.client.host if websocket.client else "") as refusal:
        if refusal is not None:  # refused before the handshake: the connection ends with this answer
            runtime.metrics.reject("overloaded")
            await _refuse(websocket, error_response(503, "overloaded", refusal, {"Retry-After": str(RETRY_AFTER_S)}))
            return
        await websocket.accept()
        try:
            options, warm_start = _options(websocket)
            await _serve(websocket, runtime, stream_bytes, options, warm_start)
        except _Closing as closing:
            if closing.error is not None:
                await websocket.send_text(json.dumps({"error": {"code": closing.error, "message": closing.reason}}))
            await websocket.close(code=closing.code, reason=closing.reason[:120])
        except WebSocketDisconnect:
            return
        finally:  # its images are freed: give their memory back (glibc keeps large freed buffers)
            freed: FreedMemory = websocket.app.state.freed_memory
            freed.soon()


async def _refuse(websocket: WebSocket, answer: Response) -> None:
    """Refuse the handshake with the HTTP `answer`, where the server sends one (the ASGI WebSocket
    denial response: uvicorn does); else close it unopened (the server answers 403)."""
    if "websocket.http.response" in websocket.scope.get("extensions", {}):
        await websocket.send_denial_response(answer)
    else:
        await websocket.close(code=POLICY_VIOLATION, reason=bytes(answer.body).decode()[:120])


def _options(websocket: WebSocket) -> tuple[DisparityOptions, WarmStart]:
    """The stream's options from the query string (an error message and close where invalid)."""
    items = websocket.query_params.multi_items()
    repeated = repeated_option(items)
    if repeated is not None:
        raise _Closing(POLICY_VIOLATION, "invalid_request", repeated)
    query = dict(items)
    warm_iters = query.pop("warm_iters", None)
    try:
        options = DisparityOptions.model_validate(query)
        frames = WarmStart(options.inference, warm_iters)  # the stream's options, read once
    except ValidationError as error:
        raise _Closing(POLICY_VIOLATION, "invalid_request", validation_problems(error.errors(), ("query",))) from None
    except ValueError as error:
        raise _Closing(POLICY_VIOLATION, "invalid_request", f"query.warm_iters: {error}") from None
    problem = options.calibration_problem(calibrated=False)
    if problem is not None:
        raise _Closing(POLICY_VIOLATION, "invalid_request", f"{problem}; a stream's pairs are rectified")
    return options, frames


async def _serve(
    websocket: WebSocket, runtime: ServiceRuntime, budget: ByteBudget, options: DisparityOptions, frames: WarmStart
) -> None:
    settings = runtime.settings
    limits = ImageLimits(options.model, settings.pixel_limit(options.model), settings.min_image_side)
    largest = largest_stream_image(limits.max_pixels, settings.max_body_bytes, settings.max_stream_image_bytes)
    timeout_s = settings.stream_idle_timeout_s
    index = 0
    while True:
        with ExitStack() as holding:  # the pair's images count against the streams' budget until it is answered
            try:
                left = await _image(websocket, timeout_s, "left", largest)
            except TimeoutError:
                raise _Closing(1000, None, f"no frame for {timeout_s:g} s") from None
            holding.enter_context(_held(budget, left))
            try:
                right = await _image(websocket, timeout_s, "right", largest)
            except TimeoutError:
                raise _Closing(
                    POLICY_VIOLATION,
                    "body_timeout",
                    f"the right image did not follow the left one within {timeout_s:g} s",
                ) from None
            holding.enter_context(_held(budget, right))
            try:
                await _answer(websocket, runtime, options, frames, limits, left, right)
            except (UploadError, ApiError, BatchingError) as error:
                status, code, message = _error(error)
                await websocket.send_text(json.dumps({"error": {"code": code, "message": message}, "frame": index}))
                logger.info("stream frame refused", extra={"status": status, "code": code, "frame": index})
                if code in ("draining", "unavailable"):  # no later frame can be computed here
                    raise _Closing(GOING_AWAY if code == "draining" else TRY_AGAIN_LATER, None, message) from None
        index += 1


async def _image(websocket: WebSocket, timeout_s: float, side: str, largest: int) -> bytes:
    """The next message, which must be an image file (binary) of at most `largest` bytes."""
    async with asyncio.timeout(timeout_s):
        message = await websocket.receive()
    if message["type"] == "websocket.disconnect":
        raise WebSocketDisconnect(message.get("code", 1000))
    data: bytes | None = message.get("bytes")
    if data is None:
        raise _Closing(UNSUPPORTED_DATA, "invalid_message", f"expected the {side} image as a binary message, got text")
    if len(data) > largest:
        raise _Closing(
            MESSAGE_TOO_BIG,
            "image_too_large",
            f"the {side} image file has {len(data)} bytes; a stream's image file has {largest} at most "
            "(the model's pixel limit and the server's stream image size)",
        )
    return data


@contextmanager
def _held(budget: ByteBudget, data: bytes) -> Iterator[None]:
    """Count `data` against the streams' byte budget during the block; where it does not fit, end
    the stream (1013 `overloaded`)."""
    if not budget.take(len(data)):
        raise _Closing(TRY_AGAIN_LATER, "overloaded", budget.refusal(len(data)))
    try:
        yield
    finally:
        budget.give_back(len(data))


async def _answer(
    websocket: WebSocket,
    runtime: ServiceRuntime,
    options: DisparityOptions,
    frames: WarmStart,
    limits: ImageLimits,
    left_bytes: bytes,
    right_bytes: bytes,
) -> None:
    """Compute one pair and send its answer."""

    async def never() -> Exception:  # a frame's images are read whole: nothing abandons them
        await asyncio.Event().wait()
        raise AssertionError("unreachable")

    batcher = runtime.batcher_for(options.model)
    header = await runtime.decoders.check_headers(left_bytes, right_bytes, limits, never)
    answer = await answer_pair(
        runtime,
        batcher,
        options,
        Upload(left_bytes, right_bytes, header, rig=None),
        stop=never,
        is_disconnected=_gone(websocket),
        frames=frames,
    )
    if options.format is OutputFormat.json:
        await websocket.send_text(answer.body.decode())
    else:
        await websocket.send_bytes(answer.body)


def _gone(websocket: WebSocket) -> Callable[[], Awaitable[bool]]:
    """Whether the client has gone (the batcher's predicate, as `Request.is_disconnected`)."""

    async def is_disconnected() -> bool:
        return websocket.client_state is WebSocketState.DISCONNECTED

    return is_disconnected


def _error(error: Exception) -> tuple[int, str, str]:
    """(HTTP status it would have, code, message) of a frame's error."""
    if isinstance(error, UploadError):
        return error.status, error.code, error.message
    if isinstance(error, BatchingError):
        error = batching_answer(error)
    assert isinstance(error, ApiError)
    return error.status, error.code, error.message
