"""With `CRESTEREO_API_KEY` set, which routes answer without the key: every route of the app is
enumerated, so that a new route cannot be added without a decision (service/README.md, "API key")."""

from __future__ import annotations

from typing import Any

import anyio
import pytest
import yaml

from service_helpers import REPO, lite_settings, serve_asgi

pytestmark = pytest.mark.anyio

KEY = "s3cret"
OPEN = {"/health", "/health/live", "/health/ready", "/metrics", "/", "/static/{name:path}", "/docs", "/openapi.json"}
"""The routes answered without the key, by decision: probes and metrics, and what is the same on
every install (the page, its files, the docs page, the contract). Every other route refuses a
request without the key; a new route is refused until it is added here and to the middleware."""
SAMPLE_PATHS = {"/models/{name}": "/models/lite", "/static/{name:path}": "/static/app.js"}
"""A real path of each route with parameters (with the key, every closed route must be found)."""
BEARER = {"Authorization": f"Bearer {KEY}"}


def every_route(routes: list[Any]) -> list[Any]:
    """The app's routes, those of included routers too (FastAPI keeps an included router as one
    entry of `app.routes`, holding its `original_router`)."""
    found = []
    for route in routes:
        inner = getattr(route, "original_router", None)
        found += every_route(inner.routes) if inner is not None else [route]
    return found


def concrete(path: str) -> str:
    if "{" not in path:
        return path
    assert path in SAMPLE_PATHS, f"route {path}: give it a sample path in SAMPLE_PATHS"
    return SAMPLE_PATHS[path]


async def websocket_handshake(app: Any, path: str, headers: dict[str, str]) -> str:
    """The app's answer to a WebSocket handshake on `path` (`websocket.accept` or
    `websocket.close`); the client leaves at once after it."""
    sent: list[dict[str, Any]] = []
    events = [{"type": "websocket.connect"}]
    scope = {
        "type": "websocket",
        "asgi": {"version": "3.0"},
        "scheme": "ws",
        "path": path,
        "raw_path": path.encode(),
        "root_path": "",
        "query_string": b"",
        "headers": [(name.lower().encode(), value.encode()) for name, value in headers.items()],
        "client": ("127.0.0.1", 50000),
        "server": ("service", 80),
        "subprotocols": [],
        "state": {},
    }

    async def receive() -> dict[str, Any]:
        return events.pop(0) if events else {"type": "websocket.disconnect", "code": 1000}

    async def send(message: dict[str, Any]) -> None:
        sent.append(message)

    with anyio.fail_after(30):
        await app(scope, receive, send)
    return sent[0]["type"]


async def test_with_a_key_every_route_but_the_open_ones_refuses_a_request_without_it():
    async with serve_asgi(lite_settings(api_key=KEY)) as h:
        routes = every_route(h.app.routes)
        seen_open = set()
        for route in routes:
            path = concrete(route.path)
            methods = getattr(route, "methods", None)
            if methods is None:  # a WebSocket route
                refused = await websocket_handshake(h.app, path, {})
                wrong = await websocket_handshake(h.app, path, {"Authorization": "Bearer s3cre"})
                accepted = await websocket_handshake(h.app, path, BEARER)
                assert route.path not in OPEN
                assert (refused, wrong, accepted) == ("websocket.close", "websocket.close", "websocket.accept"), path
                continue
            for method in methods:
                without = await h.client.request(method, path)
                if route.path in OPEN:
                    assert without.status_code == 200, (method, path, without.text)
                    seen_open.add(route.path)
                    continue
                wrong = await h.client.request(method, path, headers={"Authorization": "Bearer s3cre"})
                with_key = await h.client.request(method, path, headers=BEARER)
                for refused in (without, wrong):
                    assert refused.status_code == 401, (method, path, refused.status_code)
                    assert refused.headers["www-authenticate"] == "Bearer"
                    if method != "HEAD":
                        assert refused.json()["error"]["code"] == "unauthorized"
                # with the key the route is reached (POST /disparity without images: 415)
                assert with_key.status_code not in (401, 404), (method, path, with_key.text)
        unknown = [(await h.client.get("/nothing", headers=headers)).status_code for headers in ({}, BEARER)]
    assert seen_open == OPEN  # each open route exists and was tried
    assert {route.path for route in routes} > OPEN  # and some were closed
    assert unknown == [401, 404]  # closed by default: without the key nothing says what exists


async def test_without_a_key_every_route_is_open():
    async with serve_asgi() as h:
        answers = {path: (await h.client.get(path)).status_code for path in ("/models", "/models/lite", "/nothing")}
        stream = await websocket_handshake(h.app, "/disparity/stream", {})
    assert answers == {"/models": 200, "/models/lite": 200, "/nothing": 404}
    assert stream == "websocket.accept"


def test_the_contract_declares_the_key_on_exactly_the_routes_that_refuse_requests_without_it():
    contract = yaml.safe_load((REPO / "openapi.yaml").read_text())
    operations = [(path, method, op) for path, ops in contract["paths"].items() for method, op in ops.items()]
    assert {path for path, _, _ in operations} - OPEN == {"/disparity", "/models", "/models/{name}"}
    for path, method, operation in operations:
        keyed = path not in OPEN
        assert ({"HTTPBearer": []} in operation.get("security", [])) == keyed, (method, path)
        assert ("401" in operation["responses"]) == keyed, (method, path)
