"""Fetch the Swagger UI files that `GET /docs` serves: the npm package swagger-ui-dist, pinned.

    .venv/bin/python service/static/docs/fetch_swagger_ui.py           # the pinned version, again
    .venv/bin/python service/static/docs/fetch_swagger_ui.py 5.36.0    # pin another version

Downloads the package's tarball from the npm registry, refuses it unless its sha512 equals the
registry's `dist.integrity` (and, for the pinned version, the integrity recorded at pinning), writes
FILES beside this script and records the version, tarball, integrity and each file's sha256 in
`swagger-ui-dist.json` (a test checks the committed files against it). The files are committed, so
that building, testing and serving never need the internet; run this only to change the version.
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
import sys
import tarfile
import urllib.request
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
PIN = HERE / "swagger-ui-dist.json"
REGISTRY = "https://registry.npmjs.org/swagger-ui-dist"
FILES = ("swagger-ui-bundle.js", "swagger-ui.css", "favicon-32x32.png", "LICENSE", "NOTICE")
"""What the docs page loads (script, style, icon), and the licence it ships under (Apache-2.0)."""


def fetch(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=120) as response:
        body: bytes = response.read()
        return body


def sha512_integrity(data: bytes) -> str:
    """Subresource-integrity form of the sha512, as npm's `dist.integrity` writes it."""
    return "sha512-" + base64.b64encode(hashlib.sha512(data).digest()).decode()


def pin_version(version: str, pinned: dict[str, Any]) -> dict[str, Any]:
    """Download `version`, check it, write FILES here; the record of what was written."""
    dist = json.loads(fetch(f"{REGISTRY}/{version}"))["dist"]
    integrity: str = dist["integrity"]
    if version == pinned.get("version") and integrity != pinned["integrity"]:
        raise SystemExit(f"the registry's integrity of {version} is {integrity}, not the pinned {pinned['integrity']}")
    tarball = fetch(dist["tarball"])
    if sha512_integrity(tarball) != integrity:
        raise SystemExit(f"{dist['tarball']} does not match its integrity {integrity}: nothing written")
    with tarfile.open(fileobj=io.BytesIO(tarball), mode="r:gz") as archive:
        contents = {}
        for name in FILES:
            member = archive.extractfile(f"package/{name}")
            if member is None:
                raise SystemExit(f"no {name} in {dist['tarball']}")
            contents[name] = member.read()
    for name, data in contents.items():
        (HERE / name).write_bytes(data)
    return {
        "package": "swagger-ui-dist",
        "version": version,
        "tarball": dist["tarball"],
        "integrity": integrity,
        "files": {name: "sha256:" + hashlib.sha256(data).hexdigest() for name, data in contents.items()},
    }


def main(argv: list[str]) -> None:
    pinned: dict[str, Any] = json.loads(PIN.read_text()) if PIN.exists() else {}
    version = argv[0] if argv else pinned["version"]
    record = pin_version(version, pinned)
    PIN.write_text(json.dumps(record, indent=2) + "\n")
    print(f"swagger-ui-dist {version} ({record['integrity']}): {', '.join(FILES)} written to {HERE}")


if __name__ == "__main__":
    main(sys.argv[1:])
