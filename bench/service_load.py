"""Load benchmark of the HTTP service: throughput and latency per backend, batching on and off.

    python bench/service_load.py [--sizes 256x512 384x1248] [--concurrency 1 4 16] [--requests 12]
                                 [--backends torch openvino] [--batching on off] [--max-batch-size 8]
                                 [--threads 0]

Starts `python -m crestereo_pp.service` on a free loopback port once per backend and
batching setting, lite model only: batching on (`CRESTEREO_MAX_BATCH_SIZE=--max-batch-size`) or
off (`=1`), `CRESTEREO_BACKEND` the backend, otherwise the service's defaults (`--threads` sets
`CRESTEREO_THREADS`; 0 = the CPU quota). On OpenVINO it first waits until `GET /models` says the
graph is compiled (an export on the first run; read from the cache later). For each image size,
an untimed burst at the highest concurrency (so that the batch shapes are compiled), then for
each concurrency C, C client threads send max(--requests, 2 C) requests in all, back to back;
the table gives requests/s, client-side p50/p95/p99 latency and the mean batch size the server
reported (`X-Batch-Size`). Inputs are random smooth textures whose right view is the left shifted
by 8 px; answers are requested as npz (binary, cheap to encode and parse). It ends with the
throughput ratios against torch with batching at concurrency 16, and batching's gains. Client and
server share the machine: read the numbers with that in mind.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import cv2
import httpx
import numpy as np

from crestereo_pp.service.local import local_service


@dataclass(frozen=True)
class Cell:
    backend: str
    batching: bool
    size: tuple[int, int]
    concurrency: int
    requests: int
    seconds: float
    latencies_ms: list[float]
    batch_sizes: list[int]

    @property
    def throughput(self) -> float:
        return self.requests / self.seconds

    def percentile(self, q: float) -> float:
        return float(np.percentile(self.latencies_ms, q))


def stereo_pair_files(height: int, width: int, shift: int = 8) -> dict[str, tuple[str, bytes]]:
    rng = np.random.default_rng(0)
    coarse = rng.integers(0, 256, (height // 8 + 1, (width + shift) // 8 + 1, 3), dtype=np.uint8)
    texture = cv2.resize(coarse, (width + shift, height), interpolation=cv2.INTER_CUBIC)
    left, right = texture[:, shift:], texture[:, :width]
    return {
        name: (f"{name}.png", cv2.imencode(".png", image)[1].tobytes())
        for name, image in (("left", left), ("right", right))
    }


def server_settings(backend: str, max_batch_size: int, threads: int) -> dict[str, str]:
    """The settings of the server measured: lite only, on `backend` (OpenVINO: lite's default graphs
    exported at startup where the cache lacks them), `max_batch_size`, `threads` torch threads."""
    return {
        "CRESTEREO_MODELS": "lite",
        "CRESTEREO_BACKEND": backend,
        "CRESTEREO_EXPORT_ITERS": "default",
        "CRESTEREO_MAX_BATCH_SIZE": str(max_batch_size),
        "CRESTEREO_THREADS": str(threads),
        "CRESTEREO_LOG_LEVEL": "warning",
        "PYTHONWARNINGS": "ignore::RuntimeWarning",
    }


Answer = TypeVar("Answer")


def concurrently(send: Callable[[int], Answer], concurrency: int, requests: int) -> tuple[float, list[Answer]]:
    """`send(0)`, ..., `send(requests - 1)` from `concurrency` threads at once (the load of this
    benchmark, of ray_load.py's and of the GPU check's service stage): the burst's wall seconds and
    the answers, in order."""
    started = time.perf_counter()
    with ThreadPoolExecutor(concurrency) as pool:
        answers = list(pool.map(send, range(requests)))
    return time.perf_counter() - started, answers


def run_cell(
    base_url: str, files: dict[str, Any], concurrency: int, requests: int, two_pass: str = "auto"
) -> tuple[float, list[float], list[int], set[str]]:
    """Send `requests` requests (with `two_pass`) from `concurrency` threads; wall seconds,
    latencies, batch sizes, and the replicas that answered (`X-Replica`, behind Ray Serve; else none)."""
    limits = httpx.Limits(max_connections=concurrency)
    with httpx.Client(base_url=base_url, timeout=600, limits=limits) as client:

        def one(_: int) -> tuple[float, int, str | None]:
            started = time.perf_counter()
            response = client.post("/disparity", params={"format": "npz", "two_pass": two_pass}, files=files)
            response.raise_for_status()
            headers = response.headers
            return (time.perf_counter() - started) * 1000, int(headers["x-batch-size"]), headers.get("x-replica")

        seconds, results = concurrently(one, concurrency, requests)
    replicas = {replica for *_, replica in results if replica is not None}
    return seconds, [latency for latency, *_ in results], [batch for _, batch, _ in results], replicas


def wait_compiled(base_url: str, files: dict[str, Any], two_pass: str, timeout_s: float = 600.0) -> None:
    """One request, then poll `GET /models/lite` until its default iterations run on the backend
    (the server exports them at startup where they are not cached)."""
    run_cell(base_url, files, 1, 1, two_pass)
    deadline = time.monotonic() + timeout_s
    while not httpx.get(f"{base_url}/models/lite", timeout=10).json()["compiled"]:
        if time.monotonic() > deadline:
            raise TimeoutError(f"lite was not compiled within {timeout_s:.0f} s")
        time.sleep(2)


def measure(backend: str, batching: bool, args: argparse.Namespace, log_dir: Path) -> list[Cell]:
    settings = server_settings(backend, args.max_batch_size if batching else 1, args.threads)
    cells = []
    log_path = log_dir / f"uvicorn-{backend}-batch{settings['CRESTEREO_MAX_BATCH_SIZE']}.log"
    with log_path.open("wb") as log, local_service(settings, log, ready_timeout_s=120) as server:
        base_url = server.base_url
        for height, width in args.sizes:
            files = stereo_pair_files(height, width)
            if backend == "openvino":
                wait_compiled(base_url, files, args.two_pass)
            top = max(args.concurrency)
            warm_up = max(2, 2 * top if batching else 2)
            run_cell(base_url, files, top, warm_up, args.two_pass)  # warm-up: compiles the batch shapes
            for concurrency in args.concurrency:
                requests = max(args.requests, 2 * concurrency)
                seconds, latencies, batches, _ = run_cell(base_url, files, concurrency, requests, args.two_pass)
                cell = Cell(backend, batching, (height, width), concurrency, requests, seconds, latencies, batches)
                cells.append(cell)
                print(row(cell), flush=True)
    return cells


def row(cell: Cell) -> str:
    height, width = cell.size
    return (
        f"| {cell.backend} | {'on' if cell.batching else 'off'} | {height}x{width} | {cell.concurrency} | "
        f"{cell.requests} | {cell.throughput:.2f} | {cell.percentile(50):.0f} | "
        f"{cell.percentile(95):.0f} | {cell.percentile(99):.0f} | "
        f"{statistics.mean(cell.batch_sizes):.2f} |"
    )


def parse_size(text: str) -> tuple[int, int]:
    height, width = text.lower().split("x")
    return int(height), int(width)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--sizes", nargs="+", type=parse_size, default=[(256, 512), (384, 1248)], help="HEIGHTxWIDTH image sizes"
    )
    parser.add_argument("--concurrency", nargs="+", type=int, default=[1, 4, 16])
    parser.add_argument("--requests", type=int, default=12, help="requests per cell (at least 2 x concurrency)")
    parser.add_argument("--backends", nargs="+", choices=["torch", "openvino"], default=["torch", "openvino"])
    parser.add_argument("--batching", nargs="+", choices=["on", "off"], default=["on", "off"])
    parser.add_argument("--max-batch-size", type=int, default=8, help="with batching on")
    parser.add_argument("--threads", type=int, default=0, help="CRESTEREO_THREADS (0 = CPU quota)")
    parser.add_argument(
        "--two-pass",
        choices=["auto", "true", "false"],
        default="auto",
        help="the requests' two_pass (auto: the pairs' 8 px disparities are computed enlarged 1.5x) [auto]",
    )
    args = parser.parse_args()

    cpus = os.cpu_count()
    print(f"lite model, two_pass={args.two_pass}; server and client on this machine ({cpus} CPUs); latency in ms")
    print("| backend | batching | size | concurrency | requests | req/s | p50 | p95 | p99 | mean batch |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as log_dir:
        cells = {
            (c.backend, c.batching, c.size, c.concurrency): c
            for backend in args.backends
            for batching in (setting == "on" for setting in args.batching)
            for c in measure(backend, batching, args, Path(log_dir))
        }

    top = max(args.concurrency)
    print()
    for size in args.sizes:
        reference = cells.get(("torch", True, size, top))
        for (backend, batching, cell_size, concurrency), cell in cells.items():
            if cell_size != size or concurrency != top:
                continue
            label = f"{backend}, batching {'on' if batching else 'off'}"
            if reference is not None:
                print(
                    f"{size[0]}x{size[1]}, concurrency {top}, {label}: "
                    f"{cell.throughput / reference.throughput:.2f}x the throughput of torch with batching"
                )


if __name__ == "__main__":
    main()
