"""Fixtures of the service tests (helpers live in `service_helpers.py`)."""

import pytest


@pytest.fixture
def anyio_backend() -> str:
    """The service runs on asyncio (uvicorn's loop); async tests do too."""
    return "asyncio"
