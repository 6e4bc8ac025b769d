"""The inference thread: calls in order on one daemon thread that never holds the process."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest

from crestereo_pp.service.batching.daemon_thread import DaemonThreadExecutor, any_busy
from service_helpers import REPO


def test_calls_run_in_order_on_one_named_daemon_thread_and_errors_reach_the_caller():
    seen: list[tuple[int, str, bool]] = []
    worker = DaemonThreadExecutor("inference-test", initializer=seen.append, initargs=((0, "init", True),))

    def call(n: int) -> int:
        thread = threading.current_thread()
        seen.append((n, thread.name, thread.daemon))
        return n * 10

    futures = [worker.submit(call, n) for n in (1, 2, 3)]
    assert [f.result(timeout=10) for f in futures] == [10, 20, 30]
    assert seen == [(0, "init", True)] + [(n, "inference-test", True) for n in (1, 2, 3)]
    with pytest.raises(ZeroDivisionError):
        worker.submit(lambda: 1 / 0).result(timeout=10)
    worker.shutdown()
    with pytest.raises(RuntimeError, match="shut down"):
        worker.submit(call, 4)


def test_busy_is_true_exactly_while_a_call_runs():
    release = threading.Event()
    worker = DaemonThreadExecutor("inference-test")
    started = threading.Event()
    future = worker.submit(lambda: (started.set(), release.wait(10)))
    assert started.wait(10)
    assert worker.busy and any_busy()
    release.set()
    future.result(timeout=10)
    worker.shutdown()
    assert not worker.busy


@pytest.mark.slow
def test_a_process_can_exit_while_its_worker_waits_for_work():
    script = (
        "from crestereo_pp.service.batching.daemon_thread import DaemonThreadExecutor\n"
        "import torch\n"
        "w = DaemonThreadExecutor('inference')\n"
        "w.submit(torch.nn.functional.conv2d, torch.randn(1, 8, 64, 64), torch.randn(8, 8, 3, 3)).result()\n"
    )
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
