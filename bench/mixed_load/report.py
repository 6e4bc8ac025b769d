"""The tables printed at the end: RSS at the start, every minute and at the end with the slope over
the last half of the run; `/health/live` probe times; the answers by job, status, code and verdict."""

from __future__ import annotations

import statistics
from collections import Counter
from collections.abc import Callable

import numpy as np

from .jobs import Outcome
from .memory import Sample

VERDICTS = ("ok", "expected", "shed", "unexpected")


def slope_mib_per_min(samples: list[Sample], key: Callable[[Sample], float]) -> float:
    """Least-squares slope over the last half of the run."""
    if len(samples) < 3:
        return float("nan")
    half = samples[-1].t / 2
    tail = [s for s in samples if s.t >= half]
    t = np.array([s.t for s in tail])
    y = np.array([key(s) for s in tail])
    return float(np.polyfit(t, y, 1)[0] * 60) if len(tail) >= 2 else float("nan")


def memory_table(samples: list[Sample]) -> str:
    def nearest(t: float) -> Sample:
        return min(samples, key=lambda s: abs(s.t - t))

    marks = [samples[0], *(nearest(60.0 * minute) for minute in range(1, int(samples[-1].t // 60) + 1)), samples[-1]]
    lines = [
        "| t (s) | server RSS (MiB) | children RSS (MiB) | total (MiB) | /health/live (ms) |",
        "|---|---|---|---|---|",
    ]
    for s in {id(mark): mark for mark in marks}.values():
        live = "-" if s.live_ms is None else f"{s.live_ms:.0f}"
        lines.append(
            f"| {s.t:.0f} | {s.server_mib:.0f} | {s.children_mib:.0f} | {s.server_mib + s.children_mib:.0f} | {live} |"
        )
    peak = max(samples, key=lambda s: s.server_mib)
    lives = [s.live_ms for s in samples if s.live_ms is not None]
    slopes = (
        f"; slope over the last half: server {slope_mib_per_min(samples, lambda s: s.server_mib):+.1f} MiB/min, "
        f"children {slope_mib_per_min(samples, lambda s: s.children_mib):+.1f} MiB/min"
        if samples[-1].t >= 60
        else ""
    )
    lines.append("")
    lines.append(
        f"peak server RSS {peak.server_mib:.0f} MiB at {peak.t:.0f} s{slopes}; /health/live max "
        f"{max(lives, default=float('nan')):.0f} ms, failed {sum(s.live_ms is None for s in samples)}"
    )
    return "\n".join(lines)


def probe_summary(samples: list[Sample]) -> str:
    """The `/health/live` probes' times (the `bodies` scenario probes every 0.2 s) and the peak RSS."""
    lives = [s.live_ms for s in samples if s.live_ms is not None]
    peak = max(samples, key=lambda s: s.server_mib + s.children_mib)
    failed = sum(s.live_ms is None for s in samples)
    times = (
        f"p50 {np.percentile(lives, 50):.0f} ms, p99 {np.percentile(lives, 99):.0f} ms, max {max(lives):.0f} ms"
        if lives
        else "none answered"
    )
    return (
        f"/health/live: {len(lives)} probes, {times}, failed {failed}; "
        f"peak RSS server {peak.server_mib:.0f} MiB + children {peak.children_mib:.0f} MiB at {peak.t:.1f} s"
    )


def outcome_table(outcomes: list[Outcome]) -> str:
    counts = Counter((o.job, o.status, o.code, o.verdict) for o in outcomes)
    lines = ["| job | status | code | verdict | count |", "|---|---|---|---|---|"]
    for (job, status, code, verdict), n in sorted(counts.items()):
        lines.append(f"| {job} | {status} | {code} | {verdict} | {n} |")
    verdicts = Counter(o.verdict for o in outcomes)
    ok_seconds = [o.seconds for o in outcomes if o.verdict == "ok"]
    lines.append("")
    lines.append(
        f"{len(outcomes)} answers: "
        + ", ".join(f"{v} {verdicts[v]}" for v in VERDICTS)
        + (f"; ok latency p50 {statistics.median(ok_seconds):.1f} s, max {max(ok_seconds):.1f} s" if ok_seconds else "")
    )
    return "\n".join(lines)
