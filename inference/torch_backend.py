"""The torch backend's precision: bf16 autocast, under which ``StereoPredictor.forward`` runs the
network eagerly (the reference the other backends are measured against; ``inference.cuda_graphs``
replays it on CUDA) and training computes its steps."""

from __future__ import annotations

import contextlib
from typing import Any

import torch


def autocast_bf16(device: torch.device, enabled: bool, *, cache: bool = True) -> contextlib.AbstractContextManager[Any]:
    """bf16 autocast on `device` when `enabled`, else nothing (so that any device, "meta"
    included, runs in float32). cache: reuse each weight's bf16 copy within the context (off
    for a forward that a CUDA graph captures, as the PyTorch CUDA-graph notes ask)."""
    if not enabled:
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16, cache_enabled=cache)
