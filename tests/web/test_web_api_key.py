"""A key holder uses the page and the docs of a server that sets `CRESTEREO_API_KEY`: the page asks
for the key, sends it to the API only, and keeps it for the tab's session."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from service_helpers import run_uvicorn

expect = pytest.importorskip(
    "playwright.sync_api", reason="the playwright package is missing (pip install -e '.[test]')"
).expect

KEY = "s3cret"
EXAMPLE = "shapes-192x128"


def test_a_key_holder_computes_a_pair_on_the_page_and_reads_the_docs(browser: Any, tmp_path: Path) -> None:
    sent: list[tuple[str, str | None]] = []  # (path, Authorization header) of every request of the page
    with run_uvicorn(tmp_path, api_key=KEY) as server:
        context = browser.new_context(viewport={"width": 1280, "height": 900})
        try:
            page = context.new_page()
            page.set_default_timeout(30_000)
            page.on(
                "request",
                lambda request: sent.append(
                    (request.url.removeprefix(server.base_url).split("?")[0], request.headers.get("authorization"))
                ),
            )
            page.goto(server.base_url + "/")
            expect(page.locator("#model-info")).to_contain_text("enter the service's API key")
            page.fill("#api-key", KEY)
            page.wait_for_selector("#model option[value=lite]", state="attached")  # the next retry has the key
            page.select_option("#example", EXAMPLE)
            expect(page.locator("#status")).to_contain_text("loaded")
            page.click("#run")
            page.wait_for_selector("#results", state="visible")
            assert page.is_hidden("#error")
            # kept for this tab: a reload lists the models at once, and the docs load in it
            page.reload()
            expect(page.locator("#api-key")).to_have_value(KEY)
            page.wait_for_selector("#model option[value=lite]", state="attached")
            page.goto(server.base_url + "/docs")
            expect(page.locator(".opblock-post .opblock-summary-path[data-path='/disparity']")).to_be_visible()
        finally:
            context.close()
    bearing = {path for path, header in sent if header == f"Bearer {KEY}"}
    assert bearing == {"/models", "/disparity"}  # the API's calls, and nothing else
    assert ("/models", None) in sent  # the first listing, before the key was entered
