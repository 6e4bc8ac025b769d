"""The torch backend: the network run eagerly, in float32 or under bf16 autocast (the reference
the other backends are measured against; ``inference.cuda_graphs`` replays it on CUDA)."""

from __future__ import annotations

import contextlib
from typing import Any

import torch
from torch import Tensor

from crestereo_pp.model.network import CREStereoPP

from .forward import Maps
from .options import StageCounts


def autocast_bf16(device: torch.device, enabled: bool, *, cache: bool = True) -> contextlib.AbstractContextManager[Any]:
    """bf16 autocast on `device` when `enabled`, else nothing (so that any device, "meta"
    included, runs in float32). cache: reuse each weight's bf16 copy within the context (off
    for a forward that a CUDA graph captures, as the PyTorch CUDA-graph notes ask)."""
    if not enabled:
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16, cache_enabled=cache)


def eager_forward(
    network: CREStereoPP,
    device: torch.device,
    left: Tensor,
    right: Tensor,
    init: Tensor | None,
    iters: StageCounts,
    bf16: bool,
) -> Maps:
    """`network` (on `device`), eagerly, on padded (B, 3, H, W) images in [0, 255] (H, W
    multiples of 32) and an optional (B, 1, H, W) warm start (px), under bf16 autocast when
    `bf16`: disparity and uncertainty, float32 (B, 1, H, W)."""
    with autocast_bf16(device, bf16, cache=False):
        out = network(left, right, iters=iters, init_disparity=init)
    return out.disparity.float(), out.uncertainty.float()
