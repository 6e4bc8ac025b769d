"""Wall-clock timing shared by the benchmarks: model_speed.py's rows and the GPU check's inference
table (gpu_check/stages/bench.py) time their calls with `timed_calls`. Standard library only, so
that it imports wherever a benchmark runs."""

from __future__ import annotations

import math
import time
from collections.abc import Callable


def timed_calls(call: Callable[[], object], runs: int, max_seconds: float = math.inf, min_runs: int = 0) -> list[float]:
    """Wall seconds of each call of `call()`, one after another: `runs` calls, or fewer once the
    timed calls have taken `max_seconds` and at least min(min_runs, runs) are timed. A call that
    computes on a GPU must wait for its result (e.g. copy it to the host) to be timed whole."""
    times: list[float] = []
    least = min(min_runs, runs)
    while len(times) < runs and (len(times) < least or sum(times) < max_seconds):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return times
