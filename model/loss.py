"""Training loss (paper eq. 6): gamma-weighted L1 over every prediction of every stage."""

from __future__ import annotations

import torch
from torch import Tensor


def sequence_loss(
    predictions: list[list[Tensor]],
    gt: Tensor,
    valid: Tensor,
    gamma: float = 0.8,
    max_disparity: float = 512.0,
) -> Tensor:
    """L = sum_s sum_i gamma^(n_s - i) * mean over valid pixels of |d_gt - d_i^s|.

    Args:
        predictions: per stage, per iteration, (B, 1, H, W) full-resolution disparities
            (``NetworkOutput.predictions``); the last of each stage gets weight 1.
        gt: (B, 1, H, W) ground-truth disparity in pixels (may hold inf/nan where invalid).
        valid: (B, 1, H, W) bool; a pixel counts when valid and 0 < gt < max_disparity.
    Returns:
        scalar loss (pixels).
    """
    mask = valid & (gt > 0) & (gt < max_disparity)
    gt = torch.where(mask, gt, 0.0)  # no inf/nan may reach the backward pass
    count = mask.sum().clamp(min=1)
    total = gt.new_zeros(())
    for stage in predictions:
        n = len(stage)
        for i, prediction in enumerate(stage):
            error = torch.where(mask, (prediction - gt).abs(), 0.0)
            total = total + gamma ** (n - 1 - i) * error.sum() / count
    return total
