"""The service as a child process on loopback: `python -m crestereo_pp.service` on a free port, waited for until
ready, and stopped again. For the tools that need a real server beside them: benchmarks, the GPU
check, tests. Only the standard library and httpx, so that it imports where fastapi is missing.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import httpx

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class LocalService:
    """A running `python -m crestereo_pp.service`."""

    base_url: str
    process: subprocess.Popen[bytes]

    def stop(self, timeout_s: float = 30) -> None:
        """SIGTERM (the service drains), then SIGKILL after `timeout_s`."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def start_service(
    settings: Mapping[str, str],
    log: IO[bytes] | None = None,
    ready_timeout_s: float = 90,
    command: Sequence[str] = ("-m", "crestereo_pp.service"),
) -> LocalService:
    """`python -m crestereo_pp.service` (or `python COMMAND`, a command that takes --host and --port, such as
    `-m cli.main serve --ray`) from this tree on a free loopback port, with the environment plus
    `settings` (`CRESTEREO_*` variables), its output to `log`; returns once `/health/ready` answers
    200. Raises RuntimeError (the process stopped) when it exits or is not ready in time."""
    port = free_port()
    process = subprocess.Popen(
        [sys.executable, *command, "--host", "127.0.0.1", "--port", str(port)],
        cwd=REPO,
        env={**os.environ, **settings},
        stdout=log,
        stderr=subprocess.STDOUT if log is not None else None,
    )
    service = LocalService(f"http://127.0.0.1:{port}", process)
    deadline = time.monotonic() + ready_timeout_s
    while True:
        if process.poll() is not None:
            raise RuntimeError(f"the service exited with status {process.returncode} before it was ready")
        if time.monotonic() > deadline:
            service.stop()
            raise RuntimeError(f"the service was not ready within {ready_timeout_s:g} s")
        try:
            if httpx.get(service.base_url + "/health/ready").status_code == 200:
                return service
        except httpx.TransportError:
            pass
        time.sleep(0.1)


@contextmanager
def local_service(
    settings: Mapping[str, str],
    log: IO[bytes] | None = None,
    ready_timeout_s: float = 90,
    command: Sequence[str] = ("-m", "crestereo_pp.service"),
) -> Iterator[LocalService]:
    """`start_service` for the duration of a `with` block, stopped at its end."""
    service = start_service(settings, log, ready_timeout_s, command)
    try:
        yield service
    finally:
        service.stop()
