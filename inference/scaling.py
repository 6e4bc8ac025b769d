"""The pair the network sees at ``scale`` < 1 (``predict(..., scale=...)``), and the antialiased
shrinking of images that it and the quick and half-resolution passes of two-pass use."""

from __future__ import annotations

from torch import Tensor
from torch.nn import functional as F

from .options import parse_scale

MIN_SCALED_SIDE = 16
"""With ``scale``, the pair the network sees keeps at least this many pixels per side: below it
the network sees too little to match, and its disparities, multiplied by 1 / scale, come out
wider than the image."""


def scaled_size(height: int, width: int, scale: float) -> tuple[int, int]:
    """(height, width) of a ``height`` x ``width`` pair resized by ``scale`` in (0, 1], as
    ``predict(..., scale=...)`` runs it; ValueError where a side would fall below MIN_SCALED_SIDE
    (an image already smaller than that must come at scale 1)."""
    size = (round(height * parse_scale(scale)), round(width * scale))
    if scale < 1.0 and min(size) < MIN_SCALED_SIDE:
        raise ValueError(
            f"scale {scale:g} would run the {width}x{height} pair at {size[1]}x{size[0]}; "
            f"each side must stay at least {MIN_SCALED_SIDE} px (use a larger scale)"
        )
    return size


def shrink(images: Tensor, size: tuple[int, int]) -> Tensor:
    """(B, 3, H, W) images resized down to ``size`` = (height, width), antialiased."""
    return F.interpolate(images, size=size, mode="bilinear", antialias=True, align_corners=False)
