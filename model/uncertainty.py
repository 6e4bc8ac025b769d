"""Uncertainty estimation of UGAC (paper eq. 4) and its ablation variants.

U_n is computed from iteration n's cost volume and scales iteration n+1's warping offsets.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .config import Uncertainty


def volume_variance(volume: Tensor) -> Tensor:
    """Variance of the cost volume over its channels: (B, K, h, w) -> (B, 1, h, w), >= 0."""
    return volume.var(dim=1, unbiased=False, keepdim=True)


def estimate_uncertainty(mode: Uncertainty, volume: Tensor, left: Tensor, warped_right: Tensor) -> Tensor:
    """U_n in [0, 1], (B, 1, h, w): high where matching is ambiguous.

    ``variance_sigmoid`` (the paper's choice): U = 1 - sigmoid(var(V)). A flat volume (no
        preferred candidate) gives 0.5; a peaked one tends to 0. So U <= 0.5 by construction.
    ``variance_tanh``: U = 1 - tanh(var(V)), in (0, 1]; a flat volume gives 1.
    ``error_aware``: U = 2 sigmoid(e) - 1 with e = mean_c |F_L - F^_R|, the feature matching error
        at the current disparity (our reading of the paper's "error-aware" row), in [0, 1).

    Args:
        volume: (B, K, h, w) cost volume V_n.
        left, warped_right: (B, C, h, w) features the volume was built from (``error_aware`` only).
    """
    if mode == "variance_sigmoid":
        return 1.0 - torch.sigmoid(volume_variance(volume))
    if mode == "variance_tanh":
        return 1.0 - torch.tanh(volume_variance(volume))
    if mode == "error_aware":
        error = (left - warped_right).abs().mean(dim=1, keepdim=True)
        return 2.0 * torch.sigmoid(error) - 1.0
    raise ValueError(f"unknown uncertainty mode {mode!r}")
