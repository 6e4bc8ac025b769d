"""Suite-wide setup, run before any test module imports torch.

OpenMP threads that spin while waiting turn 10-50x slower when the cores are oversubscribed,
which the suite does on purpose (a pytest process beside uvicorn servers and trainers on two
cores). Passive waiting keeps every process at its normal speed; children inherit it.

The suite runs on torch, the reference backend: `backend="auto"` would otherwise export an
OpenVINO graph (a minute of CPU) in every process that predicts. The OpenVINO tests ask for it by
name, with their own cache folder.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ["CRESTEREO_BACKEND"] = "torch"

import pytest  # noqa: E402  (after the environment above, as the docstring says)

# The fixtures of the shared helpers, for every folder: servers (and asyncio for anyio), browsers.
pytest_plugins = ["service_helpers", "web_helpers"]

SLOW_FIXTURES = {"default_server", "browser", "web"}  # a real uvicorn process, Chromium
SLOW_FOLDERS = ("container",)  # a Docker engine and image
SLOW_MODULES = {
    "test_train_distributed.py",
    "test_gpu_check.py",
    "test_service_schemathesis.py",
    "test_ray_serve.py",  # a local Ray cluster
    "test_ray_predict.py",
}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark `slow` every test that starts a server, a browser, a container or another process
    (through the fixtures above, in the modules above, or marked so itself): `make test-fast`
    leaves them out for the inner loop; `make test` (and CI) runs everything."""
    for item in items:
        path = item.path
        if (
            SLOW_FIXTURES & set(getattr(item, "fixturenames", ()))
            or path.name in SLOW_MODULES
            or path.parent.name in SLOW_FOLDERS
        ):
            item.add_marker(pytest.mark.slow)
    items.sort(key=run_order)


def run_order(item: pytest.Item) -> int:
    """Tests that run OpenVINO in this process go after the others (the order since a full run
    crashed among the data-loader tests: their workers' exits were signals to a main thread whose
    signal stack OpenVINO had left on freed memory, since mended by one Core per process,
    ``inference.openvino_backend.shared_core``), the OpenVINO backend's spec first among them (it
    starts from the session's cache empty, whichever files a command names and in whatever order),
    and the web tests last of all (Playwright's sync API after the async tests). The sort is
    stable: within each group the usual order holds."""
    if item.path.parent.name == "web":
        return 3
    if "openvino_cache" not in getattr(item, "fixturenames", ()):
        return 0
    return 1 if item.path.name == "test_openvino_backend.py" else 2


@pytest.fixture(scope="session")
def openvino_cache(tmp_path_factory: pytest.TempPathFactory):
    """One OpenVINO cache folder for the whole run: a graph exported by one test is read from
    disk by the next, as a restarted process reads it."""
    return tmp_path_factory.mktemp("openvino-cache")
