"""Training losses: the paper's eq. 6 (gamma-weighted L1 over every prediction of every stage),
and a training-only matching loss on the features (the inference network is unchanged by it)."""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.nn import functional as F


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


def matching_loss(
    left_features: Tensor,
    right_features: Tensor,
    gt: Tensor,
    valid: Tensor,
    max_disparity: float,
) -> Tensor:
    """Cross-entropy that makes the feature correlation peak at the true disparity (training only).

    At 1/s of the input resolution (s = input width / feature width) every left pixel x is
    correlated with the right features at x - k for the candidates k = 0 .. ceil(max_disparity/s),
    corr_k = <F_L(x), F_R(x - k)> / sqrt(C); a softmax over the candidates (those inside the right
    map) is pushed towards the two candidates either side of the true disparity d/s, weighted by
    linear interpolation. This is the signal the group-wise correlation (eq. 1) relies on: features
    whose correct match scores highest, which the L1 loss on the disparities teaches only weakly.

    Args:
        left_features, right_features: (B, C, h, w) FEM features of the two views.
        gt: (B, 1, H, W) ground-truth disparity in input pixels (inf/nan allowed where invalid).
        valid: (B, 1, H, W) bool. A feature pixel counts where its s x s block of ground truth is
            all valid, within (0, max_disparity), spread over at most s px (no depth edge), and its
            match lies inside the right map.
    Returns:
        scalar mean cross-entropy (nats) over the counted pixels.
    """
    b, c, h, w = left_features.shape
    scale = gt.shape[-1] / w
    candidates = math.ceil(max_disparity / scale) + 1
    mask = valid & (gt > 0) & (gt < max_disparity)
    known = torch.where(mask, gt, 0.0)
    block = int(scale)
    target = F.avg_pool2d(known, block) / scale  # (B, 1, h, w) feature px
    spread = (F.max_pool2d(known, block) + F.max_pool2d(-known, block)) / scale  # max - min
    complete = F.avg_pool2d(mask.float(), block) == 1.0
    xs = torch.arange(w, device=gt.device, dtype=gt.dtype).view(1, 1, 1, w)
    # blocks across a depth edge (spread over 1 feature px) have no single true match
    counted = complete & (spread <= 1.0) & (target < candidates - 1) & (xs - target >= 0)
    correlations = []
    for k in range(candidates):
        shifted = F.pad(right_features[..., : w - k], (k, 0)) if k else right_features
        correlations.append((left_features * shifted).sum(1, keepdim=True))
    logits = torch.cat(correlations, dim=1) / math.sqrt(c)  # (B, K, h, w)
    shifts = torch.arange(candidates, device=gt.device, dtype=gt.dtype).view(1, candidates, 1, 1)
    logits = logits.masked_fill(xs - shifts < 0, float("-inf"))  # candidates left of the right map
    weights = (1.0 - (shifts - target).abs()).clamp(min=0.0)  # two-hot: linear interpolation
    log_probabilities = torch.log_softmax(logits, dim=1)
    per_pixel = -(weights * torch.where(weights > 0, log_probabilities, 0.0)).sum(1, keepdim=True)
    return torch.where(counted, per_pixel, 0.0).sum() / counted.sum().clamp(min=1)
