"""Helpers of the service tests: the real lite model, test images, apps driven through httpx on
ASGI, and real uvicorn processes on a free loopback port."""

from __future__ import annotations

import base64
import itertools
import socket
import subprocess
import threading
import warnings
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import anyio
import cv2
import httpx
import numpy as np
import pytest
from fastapi import FastAPI
from websockets.sync.client import ClientConnection, connect

from crestereo_pp.inference import load_model
from crestereo_pp.service.api.app import create_app
from crestereo_pp.service.batching.stereo import Predictor
from crestereo_pp.service.local import start_service
from crestereo_pp.service.settings import Settings

REPO = Path(__file__).resolve().parents[2]
HEIGHT, WIDTH = 64, 96


def quiet_load_model(name: str, **kwargs: Any) -> Predictor:
    """`inference.load_model` without the warning about random weights (expected until training)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return load_model(name, **kwargs)


def stereo_pair(
    height: int = HEIGHT, width: int = WIDTH, shift: int = 4, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """A textured RGB uint8 pair whose right view is the left shifted by `shift` px."""
    rng = np.random.default_rng(seed)
    texture = cv2.resize(
        rng.integers(0, 256, (height // 4 + 1, (width + shift) // 4 + 1, 3), dtype=np.uint8),
        ((width + shift), height),
        interpolation=cv2.INTER_CUBIC,
    )
    return np.ascontiguousarray(texture[:, shift:]), np.ascontiguousarray(texture[:, :width])


def cornered_pair() -> tuple[np.ndarray, np.ndarray]:
    """The web page's smallest example pair, RGB uint8 192x128: a procedural scene with corners
    enough that the service measures its rows (`stereo_pair`'s smooth texture has too few)."""
    folder = REPO / "service" / "static" / "examples" / "shapes-192x128"
    left, right = (
        cv2.cvtColor(cv2.imread(str(folder / f"{side}.png")), cv2.COLOR_BGR2RGB) for side in ("left", "right")
    )
    return left, right


def decode_array(payload: dict[str, Any]) -> np.ndarray:
    """A map of a `format=json` answer: base64 of little-endian float32, with its shape."""
    assert payload["dtype"] == "float32" and payload["byte_order"] == "little"
    return np.frombuffer(base64.b64decode(payload["data"]), "<f4").reshape(payload["shape"])


def assert_same_maps(actual: np.ndarray, expected: np.ndarray) -> None:
    """Disparity maps of one pair computed alone and in a batch (or through the service) agree
    to float rounding: batch sizes run different kernels, whose rounding the recurrent updates
    amplify at a few pixels (up to 0.012 px seen), so the bound is on the largest difference
    (0.05 px) and, to rule out any systematic change, on the mean (0.001 px)."""
    difference = np.abs(np.asarray(actual, np.float64) - np.asarray(expected, np.float64))
    assert actual.shape == expected.shape
    assert difference.max() < 0.05 and difference.mean() < 1e-3, (difference.max(), difference.mean())


def encode(image: np.ndarray, ext: str = ".png") -> bytes:
    """Image bytes; colour input is RGB."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, data = cv2.imencode(ext, image)
    assert ok
    return data.tobytes()


def corrupt_jpeg(image: np.ndarray) -> bytes:
    """`image` as a JPEG with 10 bytes of its entropy-coded data zeroed, as a flaky link might:
    OpenCV still decodes it (libjpeg only prints a warning), into a picture with garbage in it."""
    data = bytearray(encode(image, ".jpg"))
    scan = data.index(b"\xff\xda")  # start of scan: its header, then the coded data up to the end marker
    start = scan + 2 + int.from_bytes(data[scan + 2 : scan + 4], "big")
    middle = (start + len(data) - 2) // 2
    data[middle : middle + 10] = bytes(10)
    return bytes(data)


def pair_files(left: np.ndarray, right: np.ndarray, ext: str = ".png") -> dict[str, Any]:
    return {"left": ("left" + ext, encode(left, ext)), "right": ("right" + ext, encode(right, ext))}


def lite_settings(**overrides: Any) -> Settings:
    return Settings(models=("lite",), **overrides)


class GatedPredictor:
    """The real predictor, except that `predict_pairs` first waits for `gate` (lets a test hold
    the worker busy while requests queue) and raises for an all-black left batch (fault
    injection)."""

    def __init__(self, inner: Predictor) -> None:
        self._inner = inner
        self.gate = threading.Event()
        self.gate.set()
        self.calls: list[int] = []  # batch size of each predict call

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def predict_pairs(self, lefts: Any, rights: Any, *args: Any, **kwargs: Any) -> Any:
        self.calls.append(len(lefts))
        assert self.gate.wait(timeout=60)
        if max(float(left.max()) for left in lefts) == 0:
            raise RuntimeError("injected fault: all-black left image")
        return self._inner.predict_pairs(lefts, rights, *args, **kwargs)


@dataclass
class Harness:
    app: FastAPI
    client: httpx.AsyncClient
    predictors: dict[str, GatedPredictor]


@asynccontextmanager
async def serve_asgi(
    settings: Settings | None = None, *, load_gate: threading.Event | None = None, await_ready: bool = True
) -> AsyncIterator[Harness]:
    """The app with its lifespan running, an httpx client on it, and (once loaded) its gated
    predictors. `load_gate` holds model loading back until set; `await_ready` waits for
    readiness before yielding."""
    predictors: dict[str, GatedPredictor] = {}

    def loader(name: str, **kwargs: Any) -> Predictor:
        if load_gate is not None:
            assert load_gate.wait(timeout=60)
        predictors[name] = GatedPredictor(quiet_load_model(name, **kwargs))
        return predictors[name]

    app = create_app(settings or lite_settings(), loader=loader)
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://service", timeout=60) as client:
            if await_ready:
                await wait_ready(client)
            yield Harness(app, client, predictors)


async def wait_ready(client: httpx.AsyncClient, timeout_s: float = 60) -> None:
    with anyio.fail_after(timeout_s):
        while (await client.get("/health/ready")).status_code != 200:
            await anyio.sleep(0.01)


def metric_total(text: str, name: str, **labels: str) -> float:
    """Sum of the samples `name` in a Prometheus exposition whose labels include `labels`."""
    wanted = {f'{key}="{value}"' for key, value in labels.items()}
    total = 0.0
    for line in text.splitlines():
        if line.startswith("#"):
            continue
        sample, _, value = line.rpartition(" ")
        sample_name, _, sample_labels = sample.partition("{")
        if sample_name == name and wanted <= set(sample_labels.rstrip("}").split(",")):
            total += float(value)
    return total


# --- real uvicorn processes --------------------------------------------------------------------


@dataclass
class Server:
    base_url: str
    process: subprocess.Popen[bytes]
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


_logs = itertools.count()


@contextmanager
def run_uvicorn(tmp_path: Path, **env: str) -> Iterator[Server]:
    """`python -m crestereo_pp.service` (uvicorn with the service's limits) on a free loopback port with `CRESTEREO_*`
    settings from `env` (lite only unless given); stopped (and killed if need be) on exit."""
    log_path = tmp_path / f"uvicorn-{next(_logs)}.log"
    settings = {
        "CRESTEREO_MODELS": "lite",
        "PYTHONWARNINGS": "ignore::RuntimeWarning",
        **{f"CRESTEREO_{key.upper()}": value for key, value in env.items()},
    }
    with log_path.open("wb") as log:
        try:
            service = start_service(settings, log)
        except RuntimeError as error:
            raise AssertionError(f"{error}:\n{log_path.read_text(errors='replace')}") from None
    try:
        yield Server(service.base_url, service.process, log_path)
    finally:
        service.stop()


def read_answer(sock: socket.socket) -> str:
    """One HTTP answer read off a raw socket: its head and its Content-Length body."""
    sock.settimeout(10)
    data = b""
    while b"\r\n\r\n" not in data:
        received = sock.recv(65536)
        assert received, f"the connection was closed after {data!r}"
        data += received
    head, _, body = data.partition(b"\r\n\r\n")
    length = next(
        int(line.split(b":")[1]) for line in head.split(b"\r\n") if line.lower().startswith(b"content-length")
    )
    while len(body) < length:
        received = sock.recv(65536)
        assert received, f"the connection was closed after {len(body)} of {length} bytes of the body"
        body += received
    return (head + b"\r\n\r\n" + body).decode("latin-1")


def ws_url(base_url: str, query: str = "") -> str:
    """The URL of `/disparity/stream` on the server at `base_url`, with `query`."""
    return base_url.replace("http://", "ws://") + "/disparity/stream" + (f"?{query}" if query else "")


def open_stream(base_url: str, query: str = "", source: str = "127.0.0.1") -> ClientConnection:
    """A WebSocket on `/disparity/stream` from the loopback address `source` (127.0.0.x: as many
    clients as a test needs, told apart by address)."""
    host, port = base_url.removeprefix("http://").split(":")
    sock = socket.create_connection((host, int(port)), source_address=(source, 0))
    return connect(ws_url(base_url, query), sock=sock, open_timeout=10)


# --- fixtures, imported by the conftest of every folder whose tests need a server -----------------


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
