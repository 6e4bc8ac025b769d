"""Middleware for Ray Serve's HTTP proxy (`crestereo-pp serve --ray`), imported by the proxy
through `RAY_SERVE_HTTP_PROXY_CALLBACK_IMPORT_PATH`: Starlette only, so that it loads fast."""

from __future__ import annotations

from starlette.middleware import Middleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

REPLICA_LOST_BODY = (
    b'{"error": {"code": "replica_lost", "message": "the replica computing this request stopped before '
    b'answering; it was not computed: send it again"}}'
)


def proxy_middlewares() -> list[Middleware]:
    """The callback Ray's proxy calls: its middleware."""
    return [Middleware(ProxyAnswerMiddleware)]


class ProxyAnswerMiddleware:
    """In Ray's HTTP proxy: answers as the service gives them.

    Where a replica dies before it answers, Ray's proxy ends the request with an empty 500; this
    answers the service's JSON 503 `replica_lost` with `Retry-After` instead, so that a client
    knows the request was not computed and may send it again. A header that both the proxy and
    the replica set with one value (`X-Request-Id`) is sent once."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False
        held: Message | None = None

        async def watch(message: Message) -> None:
            nonlocal started, held
            if message["type"] == "http.response.start":
                message["headers"] = list(dict.fromkeys((bytes(k), bytes(v)) for k, v in message.get("headers", [])))
            if message["type"] == "http.response.start" and message["status"] == 500 and not started:
                held = message  # Ray's own empty 500 is only sent on with a body
                return
            if held is not None:
                if message["type"] == "http.response.body" and not message.get("body") and not message.get("more_body"):
                    return  # the empty 500: replaced below
                await send(held)
                held = None
            started = True
            await send(message)

        await self.app(scope, receive, watch)
        if held is not None or not started:
            await send_replica_lost(send)


async def send_replica_lost(send: Send) -> None:
    """Answer 503 `replica_lost` (JSON, `Retry-After: 1`)."""
    await send(
        {
            "type": "http.response.start",
            "status": 503,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(REPLICA_LOST_BODY)).encode()),
                (b"retry-after", b"1"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": REPLICA_LOST_BODY})
