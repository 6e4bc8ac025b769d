"""The environment stage: torch, the device, nvidia-smi."""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
from collections.abc import Callable
from typing import Any

from ..plans import Plan, StageResult


def environment_stage(plan: Plan, deadline: float, args: argparse.Namespace, save: Callable[..., None]) -> StageResult:
    """torch's and Python's versions and the device (name, capability, memory; nvidia-smi's table in the
    log); failed on the GPU plan without a CUDA device."""
    import torch

    data: dict[str, Any] = {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "cuda": torch.version.cuda,
        "device": "cpu",
    }
    print(
        f"torch {torch.__version__} (CUDA {torch.version.cuda}), Python {platform.python_version()}, "
        f"{os.cpu_count()} CPUs, CUDA available: {torch.cuda.is_available()}"
    )
    if torch.cuda.is_available():
        properties = torch.cuda.get_device_properties(0)
        data.update(
            device=properties.name,
            capability=f"{properties.major}.{properties.minor}",
            memory_gib=round(properties.total_memory / 2**30, 1),
            multiprocessors=properties.multi_processor_count,
        )
        print(json.dumps(data))
        if shutil.which("nvidia-smi"):
            subprocess.run(["nvidia-smi"], check=False)
    if plan.device == "cuda" and not torch.cuda.is_available():
        return StageResult("failed", "no CUDA device: run with --cpu-smoke on a machine without one", data=data)
    return StageResult("passed", f"{data['device']}, torch {torch.__version__}", data=data)
