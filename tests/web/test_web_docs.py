"""`/docs` in a real browser whose network reaches the server only (a robot with no internet):
Swagger UI renders the API's operations from the files the package serves."""

from __future__ import annotations

from typing import Any

import pytest

from service_helpers import Server

expect = pytest.importorskip(
    "playwright.sync_api", reason="the playwright package is missing (pip install -e '.[test]')"
).expect


def open_docs_offline(browser: Any, server: Server) -> tuple[Any, list[str], list[str]]:
    """A new context whose every request outside `server` is aborted, with `/docs` opened in it;
    also the URLs aborted and the console's errors (a Content-Security-Policy refusal is one)."""
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    outside: list[str] = []
    errors: list[str] = []

    def only_the_server(route: Any) -> None:
        if route.request.url.startswith(server.base_url + "/"):
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort()

    context.route("**/*", only_the_server)
    page = context.new_page()
    page.set_default_timeout(30_000)
    page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.goto(server.base_url + "/docs")
    return context, outside, errors


def test_docs_render_the_operations_with_no_network_beyond_the_server(browser: Any, default_server: Server) -> None:
    context, outside, errors = open_docs_offline(browser, default_server)
    try:
        page = context.pages[0]
        operation = page.locator(".opblock-post .opblock-summary-path[data-path='/disparity']")
        expect(operation).to_be_visible()
        expect(page.locator(".opblock-get .opblock-summary-path[data-path='/models']")).to_be_visible()
        expect(page.locator(".info .title")).to_contain_text("CREStereo++ disparity service")
    finally:
        context.close()
    assert outside == []
    assert errors == []
