"""Error answers: every error is JSON `{"error": {"code", "message"}}` with a fitting status."""

from __future__ import annotations

import logging
import uuid
from collections.abc import Mapping, Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from crestereo_pp.service.api.metrics import Metrics, RejectReason
from crestereo_pp.service.api.schemas import ErrorDetail, ErrorResponse
from crestereo_pp.service.batching.batcher import (
    BatchingError,
    ClientDisconnected,
    DeadlineExceeded,
    Draining,
    InferenceFailed,
    QueueFull,
)
from crestereo_pp.service.uploads.multipart import UploadError

logger = logging.getLogger(__name__)

MAX_LISTED_PROBLEMS = 5
"""A 422 names at most this many problems of a request (then how many more there are)."""


class ApiError(Exception):
    """An error answer; `reject_reason` counts it in `crestereo_rejected_total`."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        *,
        reject_reason: RejectReason | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.reject_reason = reject_reason
        self.headers = headers or {}


def bad_input(status: int, code: str, message: str) -> ApiError:
    """A request the client must change (413 counts as `too_large`, the rest as `bad_input`)."""
    reason: RejectReason = "too_large" if status == 413 else "bad_input"
    return ApiError(status, code, message, reject_reason=reason)


def draining(message: str) -> ApiError:
    """503: the server is shutting down."""
    return ApiError(503, "draining", message, reject_reason="not_ready", headers={"Retry-After": "1"})


def client_gone(message: str) -> ApiError:
    """499: the client left; nobody reads this answer, it shows in logs and metrics."""
    return ApiError(499, "client_disconnected", message, reject_reason="disconnect")


def batching_answer(exc: BatchingError) -> ApiError:
    """The answer to a request that the batcher could not compute."""
    match exc:
        case QueueFull():
            return ApiError(
                503, "queue_full", str(exc), reject_reason="queue_full", headers={"Retry-After": str(exc.retry_after_s)}
            )
        case Draining():  # SIGTERM came after admission began, or the drain timed out
            return draining(str(exc))
        case DeadlineExceeded():
            return ApiError(
                503,
                "deadline_exceeded",
                str(exc),
                reject_reason="deadline",
                headers={"Retry-After": str(exc.retry_after_s)},
            )
        case ClientDisconnected():
            return client_gone(str(exc))
        case InferenceFailed():
            return ApiError(500, "inference_failed", str(exc))
    raise TypeError(f"no answer for {type(exc).__name__}")


def error_response(status: int, code: str, message: str, headers: Mapping[str, str] | None = None) -> JSONResponse:
    body = ErrorResponse(error=ErrorDetail(code=code, message=message))
    return JSONResponse(body.model_dump(), status_code=status, headers=headers)


def validation_problems(errors: Sequence[Any], where: tuple[str, ...] = ()) -> str:
    """The message of an `invalid_request`: each of pydantic's `errors` (at most MAX_LISTED_PROBLEMS)
    as `query.option: what it takes` (a validator's own message without pydantic's "Value error, "),
    their place prefixed by `where` (the stream validates its query as a model of its own: ("query",))."""
    problems = "; ".join(
        f"{'.'.join(str(part) for part in (*where, *error['loc']))}: {error['msg'].removeprefix('Value error, ')}"
        for error in errors[:MAX_LISTED_PROBLEMS]
    )
    if len(errors) > MAX_LISTED_PROBLEMS:
        problems += f"; and {len(errors) - MAX_LISTED_PROBLEMS} more"
    return problems


def install_error_handlers(app: FastAPI, metrics: Metrics) -> None:
    """Route every exception the app can raise to a JSON error body (registered with FastAPI's
    `exception_handler` decorator, which keeps each handler's own exception type)."""

    @app.exception_handler(ApiError)
    async def api_error(_: Request, exc: ApiError) -> JSONResponse:
        if exc.reject_reason is not None:
            metrics.reject(exc.reject_reason)
        return error_response(exc.status, exc.code, exc.message, exc.headers)

    @app.exception_handler(UploadError)
    async def upload_error(request: Request, exc: UploadError) -> JSONResponse:
        return await api_error(request, bad_input(exc.status, exc.code, exc.message))

    @app.exception_handler(BatchingError)
    async def batching_error(request: Request, exc: BatchingError) -> JSONResponse:
        return await api_error(request, batching_answer(exc))

    @app.exception_handler(RequestValidationError)
    async def validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
        metrics.reject("bad_input")
        return error_response(422, "invalid_request", validation_problems(exc.errors()))

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
        return error_response(exc.status_code, code, str(exc.detail), exc.headers)

    @app.exception_handler(Exception)
    async def unexpected_error(_: Request, exc: Exception) -> JSONResponse:
        error_id = uuid.uuid4().hex[:12]
        logger.error("unhandled error", exc_info=exc, extra={"error_id": error_id})
        return error_response(500, "internal_error", f"internal error; logged as error id {error_id}")
