"""What every backend computes: a ``Forward``, the network on padded images, and the maps it gives.

The torch eager forward (``StereoPredictor.forward``), its CUDA-graph replay
(``inference.cuda_graphs``) and the OpenVINO forward (``inference.openvino_backend``) are called
alike, so that the predictor runs any of them.
"""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

from .options import StageCounts

Maps = tuple[Tensor, Tensor]
"""(disparity, uncertainty), each float32 (B, 1, H, W) on the inputs' device."""

Forward = Callable[[Tensor, Tensor, Tensor | None, StageCounts, bool], Maps]
"""forward(left, right, init, iters, bf16): the network on (B, 3, H, W) float images in [0, 255]
(H, W multiples of 32), an optional (B, 1, H, W) warm-start disparity (px), the iterations per
stage and whether to autocast to bf16; returns the maps."""
