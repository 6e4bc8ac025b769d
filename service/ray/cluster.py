"""Joining a Ray cluster and sharing its CPUs equally: what `crestereo-pp serve --ray` (among its
replicas) and `crestereo-pp predict --ray` (among its workers) both need. Neither Ray nor the web
app is imported here at module level: Ray takes seconds to import and is optional
(`pip install 'crestereo-pp[ray]'`), and `predict --ray` has no use for FastAPI.
"""

from __future__ import annotations

import importlib.util
import logging
from typing import Any

from crestereo_pp.service.batching.cpu import usable_cpus

HAVE_RAY = importlib.util.find_spec("ray") is not None  # imported where used: it takes seconds
CPU_STEPS = 10_000
"""Ray counts resources in steps of 1/10000: a share of CPUs is a whole number of them."""
PLACEMENT_TIMEOUT_S = 60.0
"""How long `reserve_cpus` waits for the cluster to have the CPUs it asks for."""


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


def node_cpus() -> list[float]:
    """The CPUs of each live node of the connected cluster."""
    import ray

    nodes = [node for node in ray.nodes() if node.get("Alive")]  # type: ignore[no-untyped-call]
    return [float(node["Resources"].get("CPU", 0)) for node in nodes]


def cpu_share(count: int, nodes: list[float]) -> float:
    """The largest equal share of CPUs (in Ray's steps of 1/10000) of which `count` fit on
    `nodes` (each node's CPUs; a share is never split between nodes): a fraction of a CPU where
    `count` exceeds the CPUs. 1 where none fits (a cluster with no CPUs yet, that its autoscaler
    grows on demand)."""
    steps = [int(cpus * CPU_STEPS) for cpus in nodes]

    def fits(share: int) -> bool:
        return sum(node // share for node in steps) >= count

    if not fits(1):
        return 1.0
    low, high = 1, max(steps)  # fits(low); no share is larger than a node
    while low < high:
        middle = (low + high + 1) // 2
        low, high = (middle, high) if fits(middle) else (low, middle - 1)
    return low / CPU_STEPS


def cpu_threads(share: float) -> int:
    """The torch threads of one share of CPUs: its whole CPUs, at least 1."""
    return max(1, int(share))


def reserve_cpus(count: int, share: float, timeout_s: float = PLACEMENT_TIMEOUT_S) -> Any:
    """Reserve `count` shares of `share` CPUs on the connected cluster (a placement group, for
    the actors that use them); a ValueError saying what was asked for and what the cluster has
    where it cannot place them within `timeout_s` (its CPUs are busy, or too few)."""
    import ray
    from ray.util.placement_group import placement_group, remove_placement_group

    group = placement_group([{"CPU": share}] * count, strategy="PACK")
    if group.wait(timeout_seconds=timeout_s):
        return group
    remove_placement_group(group)
    nodes = node_cpus()
    free = ray.available_resources().get("CPU", 0.0)  # type: ignore[no-untyped-call]
    raise ValueError(
        f"{count} worker(s) of {share:g} CPU(s) each ({count * share:g} CPU(s) in all) could not be placed within "
        f"{timeout_s:g} s: the cluster has {sum(nodes):g} CPU(s) on {len(nodes)} node(s) "
        f"({', '.join(f'{cpus:g}' for cpus in nodes)}), {free:g} free"
    )
