"""Helpers and fixtures of the web page tests: the real app on a real uvicorn (the service tests' helpers and
`default_server` fixture) and Debian's Chromium, headless, driven by Playwright.

Playwright drives the system browser (`executable_path`); it never downloads one (no
`playwright install`). Without /usr/bin/chromium (`.ci/run` installs Debian's `chromium`) or
without the `playwright` package (the `test` extra), the browser tests are skipped, saying why.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from service_helpers import Server

CHROMIUM = Path(os.environ.get("CRESTEREO_TEST_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


@pytest.fixture(scope="session")
def browser() -> Iterator[Any]:
    """One headless Chromium for the session; skipped (with the reason) where none is installed."""
    if not CHROMIUM.exists():
        pytest.skip(
            f"no Chromium at {CHROMIUM}: install Debian's browser "
            "(apt-get install chromium chromium-driver; .ci/run does)"
        )
    sync_api = pytest.importorskip(
        "playwright.sync_api", reason="the playwright package is missing (pip install -e '.[test]')"
    )
    with sync_api.sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_FLAGS, headless=True)
        yield chromium
        chromium.close()


@dataclass
class WebPage:
    """The service's page open in a fresh browser context, with what it did recorded."""

    page: Any  # playwright.sync_api.Page
    server: Server
    requests: list[str] = field(default_factory=list)  # every URL the page requested
    page_errors: list[str] = field(default_factory=list)  # uncaught exceptions in the page's script


@pytest.fixture
def web(browser: Any, default_server: Server) -> Iterator[WebPage]:  # noqa: F811  (the fixture, by name)
    """`/` loaded (models listed, example pairs listed) in a new context that accepts downloads."""
    context = browser.new_context(accept_downloads=True, viewport={"width": 1280, "height": 900})
    page = context.new_page()
    page.set_default_timeout(30_000)
    recorded = WebPage(page, default_server)
    page.on("request", lambda request: recorded.requests.append(request.url))
    page.on("pageerror", lambda error: recorded.page_errors.append(str(error)))
    try:
        page.goto(default_server.base_url + "/")
        page.wait_for_selector("#model option[value=lite]", state="attached")
        page.wait_for_selector("#example option[value='shapes-192x128']", state="attached")
        yield recorded
        assert recorded.page_errors == [], f"the page's script failed: {recorded.page_errors}"
    finally:
        context.close()
