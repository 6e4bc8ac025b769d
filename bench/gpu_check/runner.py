"""The stage runner: a command in a process group of its own, its output copied to the log as it
comes, killed with its children when its time is up; a stage's child process and its result."""

from __future__ import annotations

import collections
import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

from .plans import REPO, StageResult


def run_logged(
    command: list[str], seconds: float, environment: dict[str, str], log: Any
) -> tuple[int | None, list[str]]:
    """Run `command` in a process group of its own, its output copied to `log` as it comes; kill
    the whole group after `seconds`. Returns the exit status (None: killed) and the last lines."""
    process = subprocess.Popen(
        command,
        cwd=REPO,
        env=environment,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        errors="replace",
        start_new_session=True,
    )
    tail: collections.deque[str] = collections.deque(maxlen=40)

    def copy() -> None:
        assert process.stdout is not None
        for line in process.stdout:
            log.write(line)
            log.flush()
            tail.append(line.rstrip("\n"))

    reader = threading.Thread(target=copy, daemon=True)
    reader.start()
    try:
        status: int | None = process.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        status = None
    reader.join(timeout=10)
    return status, list(tail)


def run_child(
    command: list[str], seconds: float, environment: dict[str, str], log: Any, result_file: Path
) -> StageResult:
    """Run a stage in a child process; its result is what it last wrote to `result_file`."""
    start = time.monotonic()
    status, tail = run_logged(command, seconds, environment, log)
    result = StageResult("failed", tail[-1] if tail else "no output")
    if result_file.is_file():
        result = StageResult(**json.loads(result_file.read_text()))
    if status is None:
        result.status, result.detail = "timed out", f"killed after {seconds:.0f} s; {result.detail}"
    elif status != 0 and result.status not in ("failed", "skipped"):
        result.status, result.detail = "failed", f"exit status {status}; {result.detail}"
    result.seconds = time.monotonic() - start
    return result
