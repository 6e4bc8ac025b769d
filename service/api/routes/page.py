"""The web page at `/`: try the service in a browser (pick, drop or choose an example pair, see
the maps with colour bars, hover for values, download every format).

Plain HTML, CSS and JavaScript shipped in `service/static/`, no build step and nothing loaded from
another origin (the page's Content-Security-Policy allows only this server). The page calls the
public API (`GET /models`, `POST /disparity`) like any other client; these routes only serve its
files and are left out of the OpenAPI contract.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse

from crestereo_pp.service.api.errors import ApiError

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"

MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".json": "application/json",
    ".png": "image/png",
}
"""The only file types served; anything else in `service/static/` (e.g. `make_assets.py`) is not."""

CONTENT_SECURITY_POLICY = (
    "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
    "connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
)
"""Nothing from another origin, no inline script: the page works offline and cannot leak."""

HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-cache",  # revalidated (ETag) so a new release's page is picked up at once
}


def static_files(root: Path = STATIC_DIR) -> dict[str, Path]:
    """URL path below `/static/` -> file, for every servable file under `root`. A fixed table
    built once: a request can only name one of these files, never walk out of the folder."""
    if not root.is_dir():
        return {}
    return {
        path.relative_to(root).as_posix(): path
        for path in sorted(root.rglob("*"))
        if path.is_file() and path.suffix in MEDIA_TYPES
    }


FILES = static_files()

router = APIRouter(include_in_schema=False)


def _file(name: str) -> FileResponse:
    path = FILES.get(name)
    if path is None:
        raise ApiError(404, "not_found", f"no file `{name}` in the web page's static files")
    return FileResponse(path, media_type=MEDIA_TYPES[path.suffix], headers=HEADERS)


@router.head("/", include_in_schema=False)
@router.get("/")
async def page() -> FileResponse:
    """The web page (`service/static/index.html`)."""
    if "index.html" not in FILES:
        raise ApiError(
            404, "not_found", f"the web page is not installed with this service (no index.html in {STATIC_DIR})"
        )
    return _file("index.html")


@router.head("/static/{name:path}", include_in_schema=False)
@router.get("/static/{name:path}")
async def static_file(name: str) -> FileResponse:
    """One of the page's files: script, style sheet, colour maps, example pairs."""
    return _file(name)
