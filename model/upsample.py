"""Convex upsampling (RAFT) and bilinear resizing of disparity maps."""

from __future__ import annotations

from torch import Tensor
from torch.nn import functional as F

UPSAMPLE_FACTOR = 4
"""Convex upsampling goes from 1/4 resolution to full resolution."""


def convex_upsample(disparity: Tensor, mask_logits: Tensor) -> Tensor:
    """Upsample x4: every fine pixel is a convex combination of its coarse 3x3 neighbourhood.

    Args:
        disparity: (B, 1, h, w) pixels of the coarse map.
        mask_logits: (B, 9 * 16, h, w) weights before the softmax over the 9 neighbours.
    Returns:
        (B, 1, 4h, 4w) disparity in pixels of the fine map (values x4).
    """
    b, _, h, w = disparity.shape
    f = UPSAMPLE_FACTOR
    weights = mask_logits.float().view(b, 1, 9, f, f, h, w).softmax(dim=2)  # float32 under bf16 autocast
    neighbours = F.unfold(f * disparity, kernel_size=3, padding=1).view(b, 1, 9, 1, 1, h, w)
    fine = (weights * neighbours).sum(dim=2)  # (B, 1, f, f, h, w)
    return fine.permute(0, 1, 4, 2, 5, 3).reshape(b, 1, f * h, f * w)


def resize_disparity(disparity: Tensor, height: int, width: int) -> Tensor:
    """Bilinear resize of (B, 1, h, w) disparity to (B, 1, height, width), values scaled by width / w."""
    resized = F.interpolate(disparity, size=(height, width), mode="bilinear", align_corners=False)
    return resized * width / disparity.shape[-1]  # tensor arithmetic: an export keeps the sizes symbolic
