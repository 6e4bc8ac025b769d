"""How many CPU threads the inference thread may use, and setting them in torch."""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import torch

CGROUP_ROOT = Path("/sys/fs/cgroup")
logger = logging.getLogger(__name__)


def cgroup_cpu_quota(root: Path = CGROUP_ROOT) -> float | None:
    """CPUs granted by the container's cgroup (v2 `cpu.max`, else v1 CFS quota); None if unlimited."""
    v2 = root / "cpu.max"
    if v2.is_file():
        quota, period = v2.read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    v1_quota, v1_period = root / "cpu" / "cpu.cfs_quota_us", root / "cpu" / "cpu.cfs_period_us"
    if v1_quota.is_file() and v1_period.is_file():
        quota_us = int(v1_quota.read_text())
        return None if quota_us <= 0 else quota_us / int(v1_period.read_text())
    return None


def usable_cpus(root: Path = CGROUP_ROOT) -> int:
    """Whole CPUs this process may use: the cgroup quota (rounded down, at least 1), capped by the
    CPUs it is allowed to run on."""
    cores = len(os.sched_getaffinity(0))
    quota = cgroup_cpu_quota(root)
    return cores if quota is None else max(1, min(cores, math.floor(quota)))


def configure_torch_threads(intra_op: int) -> None:
    """Intra-op threads for the calling thread and the process default; one inter-op thread.

    Call before any torch work: torch refuses to change the inter-op pool once it has been used.
    """
    torch.set_num_threads(intra_op)
    if torch.get_num_interop_threads() != 1:
        try:
            torch.set_num_interop_threads(1)
        except RuntimeError:
            logger.warning("torch inter-op threads already in use; left at %d", torch.get_num_interop_threads())
