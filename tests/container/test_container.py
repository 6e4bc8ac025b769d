"""The Docker image, end to end: build, start, health, a real stereo pair, a malformed request,
SIGTERM. Needs a Docker engine: skipped (with the reason) only where none can be started, and a
failure under CI (`CI` set), where `.ci/run` installs and starts one.

The image is built with `docker/build.sh` (layer cache reused: a rebuild after a code change
takes seconds), then run as it would be in production: read-only root filesystem, a CPU quota,
a memory limit, settings from `CRESTEREO_*` environment variables.
"""

from __future__ import annotations

import base64
import json
import os
import subprocess
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
IMAGE = os.environ.get("CRESTEREO_TEST_IMAGE", "crestereo-pp:test")
CONTAINER_PORT = 8000
STEREO_DEV = next(
    (
        path
        for path in (ROOT.parent / "shared" / "data" / "stereo-dev", Path("/work/shared/data/stereo-dev"))
        if path.is_dir()
    ),
    None,
)
PAIR = "middlebury2003_teddy"  # 450x375, sent at half size
CPUS = 1  # fewer than the machine's cores, so the quota (not the core count) sets the threads
DRAIN_TIMEOUT_S = 5.0
READY_TIMEOUT_S = 180.0

pytestmark = pytest.mark.container


def _run(*args: str, timeout: float = 60, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, capture_output=True, text=True, timeout=timeout, check=check)


def _unavailable(reason: str) -> None:
    if os.environ.get("CI"):
        pytest.fail(f"CI must run the container test, but: {reason}")
    pytest.skip(reason)


@pytest.fixture(scope="module")
def docker() -> None:
    """A Docker engine that answers; started here (docker/engine.sh) when installed but stopped."""
    result = subprocess.run(["bash", str(ROOT / "docker" / "engine.sh")], capture_output=True, text=True, timeout=120)
    if result.returncode != 0:
        _unavailable(f"no Docker engine can be started: {result.stderr.strip()}")


@pytest.fixture(scope="module")
def image(docker: None) -> str:
    """The service image, built from this tree (base image made locally when missing)."""
    started = time.monotonic()
    result = subprocess.run(
        ["bash", str(ROOT / "docker" / "build.sh")],
        env={**os.environ, "IMAGE": IMAGE},
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert result.returncode == 0, f"image build failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}"
    print(f"image {IMAGE} built in {time.monotonic() - started:.0f} s")
    return IMAGE


@pytest.fixture(scope="module")
def container(image: str) -> Iterator[tuple[str, str]]:
    """A running container (name, base URL), removed whatever happens."""
    name = f"crestereo-test-{uuid.uuid4().hex[:8]}"
    try:
        _run(
            "docker",
            "run",
            "--detach",
            "--name",
            name,
            "--publish",
            f"127.0.0.1::{CONTAINER_PORT}",  # a free host port, chosen by docker
            f"--cpus={CPUS}",
            "--memory=3g",
            "--read-only",
            "--tmpfs",
            "/tmp",
            "--health-interval=2s",  # the image's HEALTHCHECK command, probed more often
            "--env",
            f"CRESTEREO_DRAIN_TIMEOUT_S={DRAIN_TIMEOUT_S}",
            "--env",
            "CRESTEREO_LOG_LEVEL=info",
            image,
        )
        host_port = _run("docker", "port", name, f"{CONTAINER_PORT}/tcp").stdout.split()[0].rsplit(":", 1)[1]
        yield name, f"http://127.0.0.1:{host_port}"
    finally:
        logs = _run("docker", "logs", "--tail", "30", name, check=False)
        print(f"--- last logs of {name} ---\n{logs.stdout}{logs.stderr}")
        _run("docker", "rm", "--force", "--volumes", name, check=False)


def _state(name: str) -> dict:
    return json.loads(_run("docker", "inspect", "--format", "{{json .State}}", name).stdout)


@pytest.fixture(scope="module")
def ready(container: tuple[str, str]) -> tuple[str, str]:
    """The container once /health/ready answers 200 and docker's own health check says healthy."""
    name, url = container
    deadline = time.monotonic() + READY_TIMEOUT_S
    while True:
        state = _state(name)
        assert state["Running"], f"container exited early: {state}"
        try:
            if (
                httpx.get(f"{url}/health/ready", timeout=5).status_code == 200
                and state.get("Health", {}).get("Status") == "healthy"
            ):
                return container
        except httpx.TransportError:
            pass
        assert time.monotonic() < deadline, f"not ready after {READY_TIMEOUT_S:.0f} s: {state}"
        time.sleep(1)


def _stereo_pair() -> tuple[bytes, bytes, tuple[int, int]]:
    """A real pair from stereo-dev at half size when present, else a generated textured pair
    (the right view is the left one shifted by 8 px); PNG bytes and (height, width)."""
    if STEREO_DEV is not None and (STEREO_DEV / PAIR).is_dir():
        left, right = (cv2.imread(str(STEREO_DEV / PAIR / f"{side}.png")) for side in ("left", "right"))
        left, right = (cv2.resize(img, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA) for img in (left, right))
    else:
        rng = np.random.default_rng(0)
        left = cv2.GaussianBlur(rng.integers(0, 256, (192, 256, 3), dtype=np.uint8), (3, 3), 0)
        right = np.roll(left, -8, axis=1)
    encoded = [cv2.imencode(".png", img)[1].tobytes() for img in (left, right)]
    return encoded[0], encoded[1], left.shape[:2]


def _decode(array: dict) -> np.ndarray:
    assert array["dtype"] == "float32" and array["byte_order"] == "little"
    return np.frombuffer(base64.b64decode(array["data"]), "<f4").reshape(array["shape"])


def test_runs_as_non_root_with_read_only_code_and_weights(ready: tuple[str, str]) -> None:
    name, _ = ready
    user = _run("docker", "exec", name, "id", "-u").stdout.strip()
    assert user != "0"
    # /app holds the code and model/weights; the service user cannot change any of it.
    writable = _run("docker", "exec", name, "find", "/app", "/opt/venv", "-writable", "-print", "-quit")
    assert writable.stdout.strip() == ""


def test_threads_follow_the_cpu_quota(ready: tuple[str, str]) -> None:
    _, url = ready
    health = httpx.get(f"{url}/health", timeout=10).json()
    assert health["batching"]["torch_threads"] == CPUS, health


def test_disparity_of_a_real_pair(ready: tuple[str, str]) -> None:
    _, url = ready
    left, right, (height, width) = _stereo_pair()
    response = httpx.post(
        f"{url}/disparity",
        params={"model": "lite"},
        files={"left": ("left.png", left, "image/png"), "right": ("right.png", right, "image/png")},
        timeout=120,
    )
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["image_size"] == {"width": width, "height": height}
    disparity, uncertainty = _decode(body["disparity"]), _decode(body["uncertainty"])
    assert disparity.shape == uncertainty.shape == (height, width)
    assert np.isfinite(disparity).all() and np.isfinite(uncertainty).all()
    assert ((uncertainty >= 0) & (uncertainty <= 1)).all()


def test_lite_runs_on_openvino_from_the_graphs_the_image_carries(ready: tuple[str, str]) -> None:
    name, url = ready
    lite = httpx.get(f"{url}/models/lite", timeout=10).json()
    assert lite["backend"] == "openvino" and lite["compiled"], lite  # no export at run time
    # the default inference's every pass: one pass (and a stream's warm frames), and the second of two passes
    graphs = _run("docker", "exec", name, "find", "/opt/crestereo-cache", "-name", "*.xml").stdout.split()
    assert sorted(Path(graph).name for graph in graphs) == ["iters0-0-6.xml", "iters2-4-6.xml"], graphs


def test_malformed_request_is_a_json_4xx(ready: tuple[str, str]) -> None:
    _, url = ready
    left, _, _ = _stereo_pair()
    response = httpx.post(
        f"{url}/disparity",
        files={"left": ("left.png", left, "image/png"), "right": ("right.png", b"this is not an image", "image/png")},
        timeout=30,
    )
    assert 400 <= response.status_code < 500, response.text
    assert response.headers["content-type"].startswith("application/json")
    error = response.json()["error"]
    assert error["code"] and error["message"]


def test_sigterm_exits_cleanly_within_the_drain_timeout(ready: tuple[str, str]) -> None:
    name, _ = ready
    grace = DRAIN_TIMEOUT_S + 15  # SIGKILL (exit 137) only if the server ignores SIGTERM
    started = time.monotonic()
    _run("docker", "stop", "--time", str(int(grace)), name, timeout=grace + 30)
    elapsed = time.monotonic() - started
    state = _state(name)
    assert not state["Running"]
    assert state["ExitCode"] == 0 and not state["OOMKilled"], state
    assert elapsed < grace, f"took {elapsed:.1f} s to stop"
