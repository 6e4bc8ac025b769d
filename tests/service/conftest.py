"""Fixtures of the service tests (helpers live in `service_helpers.py`)."""

from collections.abc import Iterator

import pytest

from service_helpers import Server, run_uvicorn


@pytest.fixture
def anyio_backend() -> str:
    """The service runs on asyncio (uvicorn's loop); async tests do too."""
    return "asyncio"


@pytest.fixture(scope="session")
def default_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """One uvicorn process with the default batching settings (lite only), shared by the tests
    that do not need their own configuration."""
    with run_uvicorn(tmp_path_factory.mktemp("uvicorn")) as server:
        yield server
