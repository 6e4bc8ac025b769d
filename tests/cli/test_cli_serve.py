"""`crestereo-pp serve`: the service from the command line, as `python -m crestereo_pp.service` runs it."""

from __future__ import annotations

import httpx
import pytest

from crestereo_pp.service.local import local_service


@pytest.mark.slow
def test_serve_answers_on_the_given_port_and_stops_on_sigterm(tmp_path):
    settings = {"CRESTEREO_MODELS": "lite", "PYTHONWARNINGS": "ignore::RuntimeWarning"}
    with (
        (tmp_path / "serve.log").open("wb") as log,
        local_service(settings, log, 120, ("-m", "crestereo_pp.cli.main", "serve")) as server,
    ):
        assert httpx.get(f"{server.base_url}/health/ready").json() == {"status": "ready"}
        assert [model["name"] for model in httpx.get(f"{server.base_url}/models").json()["models"]] == ["lite"]
    assert server.process.returncode is not None
