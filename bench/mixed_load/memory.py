"""The server's memory over the run: a process of its own (the clients' threads would hold this
one's GIL, and a probe here would time them, not the server) reads the resident memory of the
server and of its descendants from /proc and times `GET /health/live`, every `period_s`."""

from __future__ import annotations

import multiprocessing
import time
from dataclasses import asdict, dataclass
from multiprocessing.queues import Queue
from multiprocessing.sharedctypes import Synchronized
from multiprocessing.synchronize import Event as EventType
from pathlib import Path
from typing import Any

import httpx


@dataclass
class Sample:
    t: float
    server_mib: float
    children_mib: float
    children: int
    live_ms: float | None
    answers: int


def rss_kib(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError):
        pass
    return 0


def descendants(pid: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(entry.name))
    found, stack = [], list(children.get(pid, []))
    while stack:
        child = stack.pop()
        found.append(child)
        stack.extend(children.get(child, []))
    return found


def take_sample(http: httpx.Client, pid: int, started: float, answers: int) -> Sample:
    """Time `GET /health/live`, then read the RSS of `pid` and of its descendants."""
    live_ms: float | None
    t0 = time.perf_counter()
    try:
        http.get("/health/live").raise_for_status()
        live_ms = (time.perf_counter() - t0) * 1000
    except httpx.HTTPError:
        live_ms = None
    kids = descendants(pid)
    return Sample(
        round(time.monotonic() - started, 1),
        rss_kib(pid) / 1024,
        sum(rss_kib(kid) for kid in kids) / 1024,
        len(kids),
        live_ms,
        answers,
    )


def sample_until_stopped(
    base_url: str,
    pid: int,
    period_s: float,
    started: float,
    verbose: bool,
    answers: Synchronized[int],
    ready: EventType,
    stop: EventType,
    results: Queue[list[dict[str, Any]]],
) -> None:
    """The sampling process: a sample every `period_s` (printed when `verbose`) until `stop`, one more
    then, and the list put on `results`."""
    samples = []
    with httpx.Client(base_url=base_url, timeout=30) as http:
        while True:
            sample = take_sample(http, pid, started, answers.value)
            samples.append(sample)
            ready.set()
            if verbose:
                live = "-" if sample.live_ms is None else f"{sample.live_ms:.0f}"
                print(
                    f"  t={sample.t:6.1f}s server {sample.server_mib:7.1f} MiB  children {sample.children_mib:6.1f} "
                    f"MiB ({sample.children})  live {live} ms  answers {sample.answers}",
                    flush=True,
                )
            if stop.wait(period_s):
                samples.append(take_sample(http, pid, started, answers.value))
                break
    results.put([asdict(sample) for sample in samples])


class Sampler:
    """Samples the server's memory and times `/health/live` every `period_s` in a process of its own
    (spawned: it imports this module by name, which bench/ on PYTHONPATH makes importable). Returns
    once the first sample is taken."""

    def __init__(self, base_url: str, pid: int, period_s: float, verbose: bool) -> None:
        context = multiprocessing.get_context("spawn")
        self.answers: Synchronized[int] = context.Value("i", 0)
        self._stop, ready = context.Event(), context.Event()
        self._results: Queue[list[dict[str, Any]]] = context.Queue()
        arguments = (base_url, pid, period_s, time.monotonic(), verbose, self.answers, ready, self._stop, self._results)
        self._process = context.Process(target=sample_until_stopped, args=arguments, name="sampler", daemon=True)
        self._process.start()
        if not ready.wait(120):
            raise RuntimeError("the sampling process did not start")

    def count(self, answers: int) -> None:
        with self.answers.get_lock():
            self.answers.value += answers

    def stop(self) -> list[Sample]:
        self._stop.set()
        rows = self._results.get(timeout=120)
        self._process.join()
        return [Sample(**row) for row in rows]
