"""Joining a Ray cluster and sharing its CPUs equally: what `crestereo-pp serve --ray` (among its
replicas) and `crestereo-pp predict --ray` (among its workers) both need. Neither Ray nor the web
app is imported here at module level: Ray takes seconds to import and is optional
(`pip install 'crestereo-pp[ray]'`), and `predict --ray` has no use for FastAPI.
"""

from __future__ import annotations

import importlib.util
import logging

from crestereo_pp.service.batching.cpu import usable_cpus

HAVE_RAY = importlib.util.find_spec("ray") is not None  # imported where used: it takes seconds


def require_ray() -> None:
    """Raise a clear error where the `ray` extra is not installed."""
    if not HAVE_RAY:
        raise ValueError("--ray needs Ray Serve: pip install 'crestereo-pp[ray]' (or 'ray[serve]')")


def connect(address: str | None) -> None:
    """Join the Ray cluster at `address` (`auto`, or the head's host:port), or start a local one
    of this machine's usable CPUs (stopped again by `ray.shutdown()`)."""
    import ray

    if address is None:
        ray.init(num_cpus=usable_cpus(), include_dashboard=False, logging_level=logging.WARNING)
    else:
        ray.init(address=address, logging_level=logging.WARNING)


def cpu_share(count: int | None) -> tuple[int, int]:
    """`count` equal shares of the connected cluster's CPUs (replicas, or workers), as (count, CPUs
    each): at least 1 CPU, and no more than its largest node has. None: one share per CPU."""
    import ray

    nodes = [node for node in ray.nodes() if node.get("Alive")]  # type: ignore[no-untyped-call]
    per_node = [int(node["Resources"].get("CPU", 0)) for node in nodes]
    if count is None:
        return max(1, sum(per_node)), 1
    return count, max(1, min(sum(per_node) // count, max(per_node, default=1)))
