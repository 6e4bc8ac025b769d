"""The pair the network sees at another size than its own: at ``scale`` < 1
(``predict(..., scale=...)``), in the quick and half-resolution passes of two-pass, and enlarged
by ``two_pass="auto"`` where its disparities are small; the resizing of the images there and of
the maps back to the pair's size."""

from __future__ import annotations

from torch import Tensor
from torch.nn import functional as F

from .forward import Maps
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


def resize_images(images: Tensor, size: tuple[int, int]) -> Tensor:
    """(B, 3, H, W) images in [0, 255] resized to ``size`` = (height, width): shrunk antialiased
    (``shrink``), enlarged bicubic (kept in [0, 255])."""
    if size[0] <= images.shape[-2] and size[1] <= images.shape[-1]:
        return shrink(images, size)
    enlarged = F.interpolate(images, size=size, mode="bicubic", align_corners=False)
    return enlarged.clamp(0.0, 255.0)


def maps_at(maps: Maps, height: int, width: int) -> Maps:
    """(B, 1, h, w) disparity (px at w) and uncertainty resized to ``height`` x ``width``
    (antialiased where smaller), the disparity's values scaled by width / w: the maps of a pair the
    network saw at another size, at the pair's own."""
    disparity, uncertainty = maps
    if disparity.shape[-2:] == (height, width):
        return maps

    def resized(values: Tensor) -> Tensor:
        return F.interpolate(values, size=(height, width), mode="bilinear", antialias=True, align_corners=False)

    return resized(disparity) * (width / disparity.shape[-1]), resized(uncertainty)
