"""The client is tested against a real server, with the service tests' helpers and fixtures."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "service"))

from service_helpers import anyio_backend, default_server  # noqa: E402,F401  (fixtures, by name)
