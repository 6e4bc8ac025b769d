"""Fixtures of the service tests (they and the helpers live in `service_helpers.py`)."""

from service_helpers import anyio_backend, default_server  # noqa: F401  (pytest finds fixtures by name)
