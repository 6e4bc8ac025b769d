"""The tests stage: pytest on the CUDA tests, run from the orchestrating process (pytest is its own
process already)."""

from __future__ import annotations

import sys
import time
from typing import Any

from ..plans import Plan, StageResult
from ..runner import run_logged


def run_tests(plan: Plan, seconds: float, environment: dict[str, str], log: Any) -> StageResult:
    """pytest on plan.tests; its last line (the counts) is the detail."""
    start = time.monotonic()
    command = [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", *plan.tests]
    status, tail = run_logged(command, seconds, environment, log)
    outcome = "timed out" if status is None else "passed" if status == 0 else "failed"
    return StageResult(outcome, tail[-1].strip("= ") if tail else "no output", time.monotonic() - start)
