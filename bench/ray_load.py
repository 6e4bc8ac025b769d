"""Throughput of the service on Ray Serve against the plain service, on this machine.

    python bench/ray_load.py [--replicas 1 2] [--backend openvino] [--size 256x512]
                             [--concurrency 16] [--requests 64]

Starts the plain service (`python -m crestereo_pp.service`, all CPUs) and then `crestereo-pp serve --ray
--replicas N` for each N (a local Ray cluster; each replica gets the CPUs over N as its threads),
lite only, on a free loopback port. Each is warmed up until every replica has answered with its
graph compiled, then C client threads send the requests back to back (`bench/service_load.py`'s
client, inputs and settings). The table gives requests/s, client-side p50/p99 latency, the mean
batch size and how many replicas answered; then each row's throughput against the plain
service's. Client, proxy and replicas share the machine: on one machine, replicas only split its
CPUs; the numbers say what the Ray layer costs, and what one more machine's replica would add.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from service_load import parse_size, run_cell, server_settings, stereo_pair_files

from crestereo_pp.service.local import local_service


def warm_up(base_url: str, files: dict[str, Any], replicas: int, timeout_s: float = 900) -> None:
    """Bursts of requests until `replicas` distinct replicas (1 for the plain service) have said
    that lite's default graph is compiled."""
    compiled: dict[str, bool] = {}
    deadline = time.monotonic() + timeout_s
    while len(compiled) < replicas or not all(compiled.values()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"not every replica compiled lite within {timeout_s:.0f} s: {compiled}")
        run_cell(base_url, files, 2 * replicas, 4 * replicas)
        for _ in range(4 * replicas):
            answer = httpx.get(f"{base_url}/models/lite", timeout=30)
            compiled[answer.headers.get("x-replica", "plain")] = answer.json()["compiled"]


def measure(
    label: str, command: Sequence[str], replicas: int, args: argparse.Namespace, log_dir: Path
) -> tuple[str, float, float, float, float, int]:
    settings = server_settings(args.backend, 8, 0)
    files = stereo_pair_files(*args.size)
    log_path = log_dir / f"{label.replace(' ', '-')}.log"
    with log_path.open("wb") as log, local_service(settings, log, 600, command) as server:
        warm_up(server.base_url, files, replicas)
        requests = max(args.requests, 2 * args.concurrency)
        seconds, latencies, batches, answered = run_cell(server.base_url, files, args.concurrency, requests)
    return (
        label,
        requests / seconds,
        float(np.percentile(latencies, 50)),
        float(np.percentile(latencies, 99)),
        statistics.mean(batches),
        max(1, len(answered)),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--replicas", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--backend", choices=["torch", "openvino"], default="openvino")
    parser.add_argument("--size", type=parse_size, default=(256, 512), help="HEIGHTxWIDTH")
    parser.add_argument("--concurrency", type=int, default=16)
    parser.add_argument("--requests", type=int, default=64)
    args = parser.parse_args()

    height, width = args.size
    print(
        f"lite on {args.backend}, {height}x{width}, {args.concurrency} clients; service, Ray and client on this "
        f"machine ({os.cpu_count()} CPUs); latency in ms"
    )
    print("| server | req/s | p50 | p99 | mean batch | replicas answering |")
    print("|---|---|---|---|---|---|")
    rows = []
    with tempfile.TemporaryDirectory() as log_dir:
        servers = [("plain service", ("-m", "crestereo_pp.service"), 1)] + [
            (f"Ray Serve, {n} replica(s)", ("-m", "crestereo_pp.cli.main", "serve", "--ray", "--replicas", str(n)), n)
            for n in args.replicas
        ]
        for label, command, replicas in servers:
            row = measure(label, command, replicas, args, Path(log_dir))
            rows.append(row)
            name, throughput, p50, p99, batch, answering = row
            print(f"| {name} | {throughput:.2f} | {p50:.0f} | {p99:.0f} | {batch:.2f} | {answering} |", flush=True)
    print()
    for name, throughput, *_ in rows[1:]:
        print(f"{name}: {throughput / rows[0][1]:.2f}x the plain service's throughput")


if __name__ == "__main__":
    main()
