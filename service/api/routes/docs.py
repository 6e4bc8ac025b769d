"""`GET /docs`: Swagger UI for the API, served from this package so that it works with no internet:
its script, style and icon are the npm package swagger-ui-dist, pinned in
`service/static/docs/swagger-ui-dist.json` and served under `/static/docs/` with the page's files.
The page runs under a Content-Security-Policy that allows this server only, and its one inline
script by its hash."""

from __future__ import annotations

import base64
import functools
import hashlib
import re

from fastapi import APIRouter
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse

router = APIRouter(include_in_schema=False)

SWAGGER_UI = "static/docs"
"""The Swagger UI files, relative to `/docs` (so that the page also works behind a path prefix)."""


@functools.cache
def docs_page(openapi_url: str, title: str) -> tuple[str, str]:
    """The page's HTML and its Content-Security-Policy: scripts, style and data from this server
    only, the page's one inline script allowed by its hash. Built once per process: it never changes."""
    page = get_swagger_ui_html(
        openapi_url=openapi_url,
        title=title,
        swagger_js_url=f"{SWAGGER_UI}/swagger-ui-bundle.js",
        swagger_css_url=f"{SWAGGER_UI}/swagger-ui.css",
        swagger_favicon_url=f"{SWAGGER_UI}/favicon-32x32.png",
    )
    html = bytes(page.body).decode()
    inline = re.findall(r"<script>(.*?)</script>", html, flags=re.S)
    hashes = " ".join(f"'sha256-{base64.b64encode(hashlib.sha256(s.encode()).digest()).decode()}'" for s in inline)
    policy = (
        f"default-src 'none'; script-src 'self' {hashes}; style-src 'self' 'unsafe-inline'; "
        "img-src 'self' data:; connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    )
    return html, policy


@router.get("/docs")
async def docs() -> HTMLResponse:
    """Swagger UI for `openapi.json`."""
    html, policy = docs_page("openapi.json", "CREStereo++ disparity service")
    return HTMLResponse(html, headers={"Content-Security-Policy": policy})
