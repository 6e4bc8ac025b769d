"""`GET /docs`: Swagger UI for the API, its script and style pinned to one release on the CDN with
subresource integrity, and the page under a Content-Security-Policy that allows nothing else."""

from __future__ import annotations

import base64
import functools
import hashlib
import re

from fastapi import APIRouter
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse

router = APIRouter(include_in_schema=False)

CDN = "https://cdn.jsdelivr.net"
SWAGGER_UI = f"{CDN}/npm/swagger-ui-dist@5.35.0"
# sha384 of the files of the npm package swagger-ui-dist 5.35.0, which the CDN serves verbatim.
SCRIPT_URL, SCRIPT_INTEGRITY = (
    f"{SWAGGER_UI}/swagger-ui-bundle.js",
    "sha384-gjRm0bEPMeTmMh5jT2cHccIwCUZSTd8YC+j0d0sXw0MdGEfScduGpSyF3ZSSLkX9",
)
STYLE_URL, STYLE_INTEGRITY = (
    f"{SWAGGER_UI}/swagger-ui.css",
    "sha384-WlYgdmXYOOBWL5apwjDEZwN+U3HmXSSu5R6V5aGxEcf7z+KuRNwBhoxKVN1i3D5I",
)


@functools.cache
def docs_page(openapi_url: str, title: str) -> tuple[str, str]:
    """The page's HTML and its Content-Security-Policy: the pinned script and style with their
    integrity, the page's one inline script allowed by its hash, data only from this server.
    Built once per process: it never changes."""
    page = get_swagger_ui_html(
        openapi_url=openapi_url,
        title=title,
        swagger_js_url=SCRIPT_URL,
        swagger_css_url=STYLE_URL,
        swagger_favicon_url="data:,",
    )
    html = (
        bytes(page.body)
        .decode()
        .replace(
            f'<script src="{SCRIPT_URL}">',
            f'<script src="{SCRIPT_URL}" integrity="{SCRIPT_INTEGRITY}" crossorigin="anonymous">',
        )
        .replace(
            f'href="{STYLE_URL}">',
            f'href="{STYLE_URL}" integrity="{STYLE_INTEGRITY}" crossorigin="anonymous">',
        )
    )
    inline = re.findall(r"<script>(.*?)</script>", html, flags=re.S)
    hashes = " ".join(f"'sha256-{base64.b64encode(hashlib.sha256(s.encode()).digest()).decode()}'" for s in inline)
    policy = (
        f"default-src 'none'; script-src {SCRIPT_URL} {hashes}; style-src {STYLE_URL} 'unsafe-inline'; "
        "img-src 'self' data:; connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    )
    return html, policy


@router.get("/docs")
async def docs() -> HTMLResponse:
    """Swagger UI for `openapi.json`."""
    html, policy = docs_page("/openapi.json", "CREStereo++ disparity service")
    return HTMLResponse(html, headers={"Content-Security-Policy": policy})
