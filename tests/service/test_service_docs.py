"""`GET /docs` works with no internet: Swagger UI's files come from the package (the pinned npm
package swagger-ui-dist in service/static/docs/), never from another host."""

from __future__ import annotations

import base64
import hashlib
import json
import re
import tomllib
from pathlib import Path
from urllib.parse import urljoin, urlsplit

import httpx
import pytest

from crestereo_pp.service.api.app import create_app
from crestereo_pp.service.api.routes.page import STATIC_DIR
from service_helpers import lite_settings

pytestmark = pytest.mark.anyio

BASE = "http://service"
DOCS_DIR = STATIC_DIR / "docs"
PIN = json.loads((DOCS_DIR / "swagger-ui-dist.json").read_text())
MEDIA_TYPES = {".js": "text/javascript", ".css": "text/css", ".png": "image/png", ".json": "application/json"}


async def test_the_docs_page_names_no_other_host_and_its_files_are_served():
    app = create_app(lite_settings())  # the app's lifespan does not run: no models needed
    async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url=BASE) as client:
        page = await client.get("/docs")
        html = page.text
        policy = page.headers["content-security-policy"]
        # every URL the page names: attributes, and the spec's URL in its inline script
        named = re.findall(r'(?:src|href)="([^"]+)"', html) + re.findall(r"url: '([^']+)'", html)
        urls = [urljoin(BASE + "/docs", url) for url in named]
        answers = {url: await client.get(url) for url in urls}
        redoc = await client.get("/redoc")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert re.findall(r"(?:https?:)?//[\w.-]+", html) == [], "the page names another host"
    assert "http" not in policy and "default-src 'none'" in policy
    script_sources = policy.split("script-src ")[1].split(";")[0].split()
    inline = re.findall(r"<script>(.*?)</script>", html, flags=re.S)
    hashes = [f"'sha256-{base64.b64encode(hashlib.sha256(body.encode()).digest()).decode()}'" for body in inline]
    assert script_sources == ["'self'", *hashes]  # each inline script by its hash, no other inline script
    assert {urlsplit(url).path for url in urls} == {
        "/static/docs/swagger-ui-bundle.js",
        "/static/docs/swagger-ui.css",
        "/static/docs/favicon-32x32.png",
        "/openapi.json",
    }
    for url, answer in answers.items():
        assert answer.status_code == 200, url
        assert answer.headers["content-type"].startswith(MEDIA_TYPES[Path(urlsplit(url).path).suffix]), url
    assert redoc.status_code == 404  # no ReDoc: it would load from a CDN


def test_the_shipped_swagger_ui_files_are_the_pinned_ones_and_package_data():
    """The files equal what fetch_swagger_ui.py recorded (sha256 of each, from the tarball whose
    sha512 matched the registry's integrity), and the wheel carries them."""
    assert PIN["package"] == "swagger-ui-dist" and PIN["integrity"].startswith("sha512-")
    assert PIN["version"] in PIN["tarball"] and PIN["tarball"].startswith("https://registry.npmjs.org/")
    for name, digest in PIN["files"].items():
        assert "sha256:" + hashlib.sha256((DOCS_DIR / name).read_bytes()).hexdigest() == digest, name
    pyproject = tomllib.loads((STATIC_DIR.parents[1] / "pyproject.toml").read_text())
    patterns = pyproject["tool"]["setuptools"]["package-data"]["crestereo_pp.service"]
    packaged = {path for pattern in patterns for path in STATIC_DIR.parent.glob(pattern)}
    assert {DOCS_DIR / name for name in [*PIN["files"], "swagger-ui-dist.json"]} <= packaged
