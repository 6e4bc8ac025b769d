"""Write the app's OpenAPI schema as YAML: `python -m crestereo_pp.service.openapi > openapi.yaml`.

`openapi.yaml` at the repository root is the contract; a test checks it equals this output.
Needs PyYAML (in the `test` extra).
"""

from __future__ import annotations

import sys
from typing import Any

import yaml

from crestereo_pp.service.api.app import create_app
from crestereo_pp.service.settings import Settings


def openapi_schema() -> dict[str, Any]:
    """The schema of an app with default settings (the schema does not depend on settings)."""
    return create_app(Settings()).openapi()


def render_yaml(schema: dict[str, Any]) -> str:
    return yaml.safe_dump(schema, sort_keys=False, allow_unicode=True, width=100)


if __name__ == "__main__":
    sys.stdout.write(render_yaml(openapi_schema()))
