"""OpenVINO exports and the startup log in the service: only the graphs its settings name are
exported, requests never start one, and the log says when the service is ready, each warning on
one line."""

from __future__ import annotations

import asyncio
import json
import logging
import subprocess
import sys
import threading
import warnings
from pathlib import Path
from typing import Any

import pytest

from crestereo_pp.service.api.app import create_app
from crestereo_pp.service.api.logs import JsonFormatter, configure_logging
from service_helpers import REPO, lite_settings, pair_files, quiet_load_model, serve_asgi, stereo_pair

pytestmark = pytest.mark.anyio


class Records(logging.Handler):
    """The records logged to one logger while attached."""

    def __init__(self) -> None:
        super().__init__(level=logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def export_processes() -> list[str]:
    """The command lines of this process's children that export a graph."""
    children = (pid for task in Path("/proc/self/task").iterdir() for pid in (task / "children").read_text().split())
    commands = (Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode() for pid in children)
    return [command for command in commands if "crestereo_pp.inference.openvino_export" in command]


async def test_requests_with_21_distinct_iterations_start_no_export(tmp_path, openvino_cache):
    # openvino_cache only orders this test with the others that run OpenVINO here (tests/conftest.py)
    left, right = stereo_pair()
    settings = lite_settings(backend="openvino", precision="fp32", cache_dir=tmp_path)
    async with serve_asgi(settings) as h:
        files = pair_files(left, right)
        requests = (h.client.post("/disparity", params={"iters": f"1,1,{n}"}, files=files) for n in range(1, 22))
        answers = await asyncio.gather(*requests)
        backend = h.predictors["lite"].openvino
        assert [answer.status_code for answer in answers] == [200] * 21
        assert (backend.exports, backend.runs, backend.fallback_runs) == (0, 0, 21)  # each on torch
        assert [thread for thread in threading.enumerate() if thread.name == "openvino-export"] == []
        assert export_processes() == []
    assert [path for path in tmp_path.rglob("*") if path.is_file()] == []


async def test_the_service_prepares_the_iterations_its_settings_name_when_it_loads_a_model():
    asked: list[Any] = []

    def loader(name: str, **kwargs: Any) -> Any:
        asked.append(kwargs["prepare_iters"])
        return quiet_load_model(name, **kwargs)

    for environment, expected in (({}, ()), ({"export_iters": "default 2,2,4 3"}, (None, (2, 2, 4), 3))):
        app = create_app(lite_settings(**environment), loader=loader)
        async with app.router.lifespan_context(app):
            await app.state.runtime.models_loaded()
        assert asked.pop() == expected


async def test_the_log_says_ready_once_the_models_are_loaded():
    records, logger = Records(), logging.getLogger("crestereo_pp.service.batching.runtime")
    logger.addHandler(records)
    try:
        async with serve_asgi():
            pass
    finally:
        logger.removeHandler(records)
    messages = [record.getMessage() for record in records.records]
    assert messages.index("model loaded") < messages.index("ready: computing requests")
    ready = records.records[messages.index("ready: computing requests")]
    assert ready.models == ["lite"]


def test_a_python_warning_is_one_log_line_that_says_where_it_came_from():
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        configure_logging("info")
        records = Records()
        logging.getLogger("py.warnings").addHandler(records)
        try:
            warnings.warn("the 'full' weights are untrained", RuntimeWarning, stacklevel=1)
        finally:
            logging.getLogger("py.warnings").removeHandler(records)
    (record,) = records.records
    line = JsonFormatter().format(record)
    entry = json.loads(line)
    assert "\n" not in line and entry["message"] == "RuntimeWarning: the 'full' weights are untrained"
    assert entry["location"].startswith(f"{__file__}:")


@pytest.mark.slow
def test_a_read_only_image_reaches_the_network_without_a_torch_warning():
    # Images decoded from bytes (as the service's decoders hand them over) are read-only arrays;
    # torch warns once per process about those, so the check runs in a process of its own.
    script = (
        "import numpy as np, torch\n"
        "from crestereo_pp.inference.prediction import as_image_batch\n"
        "image = np.frombuffer(bytes(64 * 96 * 3), np.uint8).reshape(64, 96, 3)\n"
        "assert not image.flags.writeable\n"
        "as_image_batch(image, torch.device('cpu'))\n"
    )
    done = subprocess.run(
        [sys.executable, "-W", "error", "-c", script], cwd=REPO, capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr
