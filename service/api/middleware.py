"""ASGI middleware: request ids, access log and request metrics; the pace of a client's errors;
the API key; the request size limits; the count of requests and the bytes of their bodies held at
once."""

from __future__ import annotations

import asyncio
import logging
import re
import time
import uuid
from collections import OrderedDict

from fastapi.security.utils import get_authorization_scheme_param
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from crestereo_pp.service.api.dependencies import bearer_accepted
from crestereo_pp.service.api.errors import ApiError, error_response
from crestereo_pp.service.api.logs import request_id_var
from crestereo_pp.service.api.metrics import Metrics
from crestereo_pp.service.api.query import query_too_long
from crestereo_pp.service.settings import Settings
from crestereo_pp.service.uploads.budgets import ByteBudget
from crestereo_pp.service.uploads.memory import IDLE_TRIM_DELAY_S, FreedMemory

REQUEST_ID_HEADER = "X-Request-Id"
_VALID_REQUEST_ID = re.compile(r"[A-Za-z0-9._:-]{1,128}")
_QUIET_PATHS = ("/health", "/metrics")  # probes and scrapes are logged at debug level

logger = logging.getLogger("crestereo_pp.service.access")


class RequestContextMiddleware:
    """Gives each request an id (the client's `X-Request-Id` when well-formed, else a new one),
    echoes it in the response, writes one JSON access line and counts `/disparity` answers.

    The `/disparity` route stores the model it served in the request's state (`model`,
    `batch_size`), which lands in the metrics labels and the access line.
    """

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request_id = _client_request_id(scope) or uuid.uuid4().hex
        token = request_id_var.set(request_id)
        started = time.perf_counter()
        status = 500

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                message["headers"] = [*message.get("headers", []), (b"x-request-id", request_id.encode())]
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            seconds = time.perf_counter() - started
            state = scope.get("state", {})
            path = scope["path"]
            if path == "/disparity":
                model = state.get("model", "none")
                self.metrics.requests.labels(model=model, status=str(status)).inc()
                self.metrics.latency.labels(model=model).observe(seconds)
            level = logging.DEBUG if path.startswith(_QUIET_PATHS) else logging.INFO
            logger.log(
                level,
                "request",
                extra={
                    "method": scope["method"],
                    "path": path,
                    "status": status,
                    "duration_ms": round(seconds * 1000, 2),
                    "client": scope["client"][0] if scope.get("client") else None,
                    "model": state.get("model"),
                    "batch_size": state.get("batch_size"),
                },
            )
            request_id_var.reset(token)


def _client_request_id(scope: Scope) -> str | None:
    for name, value in scope["headers"]:
        if name == b"x-request-id":
            candidate = value.decode("latin-1")
            return candidate if _VALID_REQUEST_ID.fullmatch(candidate) else None
    return None


MAX_ERROR_DELAY_S = 2.0
"""Longest a client error's answer is held back (``ClientErrorPace``)."""
MAX_PACED_CLIENTS = 10_000
"""Client addresses whose recent errors are remembered (the least recently erring are forgotten)."""


class ClientErrorPace:
    """How fast each client address may have its errors answered: `burst` at once, then `rate` a
    second (a token bucket per address; a client within it never waits). Past it, an error's answer
    is held back until the address is within its rate again, at most MAX_ERROR_DELAY_S: a client
    that repeats bad requests without pause gets `rate` answers a second per connection, however
    cheap each refusal is."""

    def __init__(self, rate: float, burst: int) -> None:
        self.rate = rate
        self.burst = burst
        self._tokens: OrderedDict[str, tuple[float, float]] = OrderedDict()  # address: (tokens, at)

    def delay(self, client: str, now: float) -> float:
        """Count one error answered to `client` at `now` (monotonic seconds): the seconds to hold it back."""
        tokens, at = self._tokens.pop(client, (float(self.burst), now))
        tokens = min(float(self.burst), tokens + (now - at) * self.rate) - 1.0
        tokens = max(tokens, -self.rate * MAX_ERROR_DELAY_S)  # a debt never holds an answer longer than that
        self._tokens[client] = (tokens, now)
        while len(self._tokens) > MAX_PACED_CLIENTS:
            self._tokens.popitem(last=False)
        return max(0.0, -tokens / self.rate)


class ClientErrorPaceMiddleware:
    """Holds back the 4xx answers of a client address past its error budget (``ClientErrorPace``).
    The answer is held after the request has ended (it holds no place among the requests in
    progress, nor any of the upload budget): its messages are kept and sent once the delay is over.
    Every other answer passes at once."""

    def __init__(self, app: ASGIApp, pace: ClientErrorPace, metrics: Metrics) -> None:
        self.app = app
        self.pace = pace
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        held: list[Message] = []

        async def send_or_hold(message: Message) -> None:
            if held or (message["type"] == "http.response.start" and 400 <= message["status"] < 500):
                held.append(message)
            else:
                await send(message)

        await self.app(scope, receive, send_or_hold)
        if not held:
            return
        delay = self.pace.delay(scope["client"][0] if scope.get("client") else "", time.monotonic())
        if delay > 0:
            self.metrics.delayed_errors.inc()
            await asyncio.sleep(delay)
        for message in held:
            await send(message)


OPEN_PATHS = frozenset({"/health", "/health/live", "/health/ready", "/metrics", "/", "/docs", "/openapi.json"})
"""Paths answered without the API key: what orchestrators and scrapers poll (the probes, the
metrics), and what is the same on every install of a release (the web page, the docs page, the
OpenAPI contract, and under OPEN_PREFIX their files): a key holder's browser loads them before it
can send the key."""
OPEN_PREFIX = "/static/"

POLICY_VIOLATION = 1008
"""WebSocket close code of a handshake refused where the server sends no HTTP answer (it answers 403)."""


class ApiKeyMiddleware:
    """With `CRESTEREO_API_KEY` set, refuses every request to a path that is not open (OPEN_PATHS,
    OPEN_PREFIX) unless it bears the key (`Authorization: Bearer <key>`): 401 `unauthorized` with
    `WWW-Authenticate: Bearer`, before it takes a place or any of the upload budget; a WebSocket
    handshake is refused with HTTP 403 `unauthorized` (JSON, the WebSocket denial response: the
    connection never opens). Closed by default: a route added later needs the key until its path is
    listed here."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or self._allowed(scope):
            await self.app(scope, receive, send)
            return
        message = "missing or wrong bearer token"
        if scope["type"] == "websocket":  # 403: what a server answers to a handshake closed unopened
            if "websocket.http.response" in scope.get("extensions", {}):  # the ASGI denial response (uvicorn)
                await error_response(403, "unauthorized", message)(scope, receive, send)
            else:
                await send({"type": "websocket.close", "code": POLICY_VIOLATION, "reason": message})
            return
        await error_response(401, "unauthorized", message, headers={"WWW-Authenticate": "Bearer"})(scope, receive, send)

    def _allowed(self, scope: Scope) -> bool:
        path: str = scope["path"]
        if path in OPEN_PATHS or path.startswith(OPEN_PREFIX):
            return True
        authorization = dict(scope["headers"]).get(b"authorization", b"").decode("latin-1")
        scheme, token = get_authorization_scheme_param(authorization)
        return bearer_accepted(self.settings, token if scheme.lower() == "bearer" else None)


MAX_HEADER_BYTES = 16 * 1024
"""Largest request header block (names and values) the app accepts: 431 beyond."""


class RequestSizeLimitMiddleware:
    """Refuses query strings over 4 KiB (`query_too_long`) with 414, header blocks over MAX_HEADER_BYTES
    with 431, and bodies over `max_bytes` with 413: at once from `Content-Length`, else as soon as
    the streamed body passes the limit (chunked uploads). A WebSocket handshake gets the same 414
    and 431 (JSON HTTP answers, before the connection opens)."""

    def __init__(self, app: ASGIApp, max_bytes: int, metrics: Metrics) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        refusal = self._refusal(scope)
        if refusal is not None:
            self.metrics.reject("too_large")
            await error_response(*refusal)(scope, receive, send)
            return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise ApiError(413, "body_too_large", self._message(), reject_reason="too_large")
            return message

        await self.app(scope, limited_receive if scope["type"] == "http" else receive, send)

    def _refusal(self, scope: Scope) -> tuple[int, str, str] | None:
        """(status, code, message) for a request whose query, headers or declared body are over
        their limits, else None."""
        too_long = query_too_long(scope.get("query_string", b""))
        if too_long is not None:
            return 414, "query_too_long", too_long
        header_bytes = sum(len(name) + len(value) for name, value in scope["headers"])
        if header_bytes > MAX_HEADER_BYTES:
            return 431, "headers_too_large", f"request headers of {header_bytes} bytes; the limit is {MAX_HEADER_BYTES}"
        declared = declared_length(scope)
        if declared is not None and declared > self.max_bytes:
            return 413, "body_too_large", self._message()
        return None

    def _message(self) -> str:
        return f"request body larger than {self.max_bytes} bytes"


def declared_length(scope: Scope) -> int | None:
    """The body's length from `Content-Length`, where given (uvicorn refuses malformed ones)."""
    declared = dict(scope["headers"]).get(b"content-length")
    return int(declared) if declared is not None and declared.isdigit() else None


class UploadBudgetMiddleware:
    """Holds each request's body against the upload budget (stream images have their own) until the
    request ends, counted as it arrives and refused at the chunk that does not fit; a body whose
    `Content-Length` does not fit in what is free when it begins is refused unread. Refused: 503
    `overloaded` with `Retry-After`. A declared length is not reserved: a client that declares
    large bodies and sends none of them (a few idle sockets) holds none of the budget."""

    def __init__(self, app: ASGIApp, budget: ByteBudget, metrics: Metrics) -> None:
        self.app = app
        self.budget = budget
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = declared_length(scope)
        if declared is not None and not self.budget.fits(declared):
            self.metrics.reject("overloaded")
            refused = self._overloaded(declared)
            response = error_response(refused.status, refused.code, refused.message, refused.headers)
            await response(scope, receive, send)
            return
        held = 0

        async def counted_receive() -> Message:
            nonlocal held
            message = await receive()
            size = len(message.get("body", b"")) if message["type"] == "http.request" else 0
            if not self.budget.take(size):
                raise self._overloaded(size)
            held += size
            return message

        try:
            await self.app(scope, counted_receive, send)
        finally:
            self.budget.give_back(held)

    def _overloaded(self, size: int) -> ApiError:
        """The 503 for a body of which `size` more bytes do not fit (the rest of it goes unread: the
        connection is closed)."""
        return ApiError(
            503,
            "overloaded",
            self.budget.refusal(size),
            reject_reason="overloaded",
            headers={"Retry-After": "1", "Connection": "close"},
        )


class ConcurrencyLimitMiddleware:
    """Answers 503 `overloaded` (JSON, with `Retry-After`) to a request arriving while
    `max_requests` others are in progress, so that a flood of uploads cannot hold every place:
    the probes under `/health` are never counted nor refused, and keep answering. When the last
    request in progress ends, what the work left free goes back to the system (`freed_memory`),
    unless another request has begun by then."""

    def __init__(self, app: ASGIApp, max_requests: int, metrics: Metrics, freed_memory: FreedMemory) -> None:
        self.app = app
        self.max_requests = max_requests
        self.metrics = metrics
        self.freed_memory = freed_memory
        self.in_progress = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"].startswith("/health"):
            await self.app(scope, receive, send)
            return
        if self.in_progress >= self.max_requests:
            self.metrics.reject("overloaded")
            await error_response(
                503,
                "overloaded",
                f"{self.in_progress} requests are in progress, the most this server takes at once",
                headers={"Retry-After": "1"},
            )(scope, receive, send)
            return
        self.in_progress += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.in_progress -= 1
            if self.in_progress == 0:
                self.freed_memory.soon(IDLE_TRIM_DELAY_S, unless=self.busy)

    def busy(self) -> bool:
        """Whether a request is in progress."""
        return self.in_progress > 0
